"""The bodies' outlines seen by virtual cameras (docs/model.md §6, *The bodies' outline from unseen views*): a bank of
rays, drawn once before a fit, through the band of pixels along the outline of a training frame's body (the posed
mesh the fit trains on, with the capture's surface) in views no camera recorded, each labelled with whether it meets
the body (the band found by rasterising the mesh, each ray's label by intersecting it). The fit asks its
silhouette there to follow the body's (``fitting.unseen.outline_terms``)."""

from __future__ import annotations

import cv2
import numpy as np
import torch
import trimesh

from fitting.data import OutlineRays
from fitting.unseen import VIRTUAL_DISTANCE
from narf.rays import rays_from_pixels
from pipelines.datasets.camera import Camera, silhouette
from pipelines.synthetic.scene import look_at

#: virtual cameras in the bank, each of a training frame drawn at random
VIEWS = 256
#: pixels a side of a virtual camera's image; it sees HALF_FIELD reaches either side of the pelvis at its distance,
#: so a pixel is about 6.6 mm at an adult's 2.2 m (the real demo's training images: 3.8 mm)
SIZE = 400
HALF_FIELD = 1.2
#: the band: pixels at most this far (in pixels, the chessboard distance) from a pixel on the outline's other side
BAND = 2
#: rays kept per view, drawn uniformly from its band
RAYS_PER_VIEW = 400
#: frames posed at a time (the posed vertices are 80 kB a frame)
CHUNK = 32


def virtual_camera(pelvis: np.ndarray, reach: float, away: np.ndarray, down: np.ndarray) -> Camera:
    """A square pinhole camera ``VIRTUAL_DISTANCE`` reaches from ``pelvis`` along the unit vector ``away``, looking
    at the pelvis, image-down about ``down``, focal f = (SIZE / 2) VIRTUAL_DISTANCE / HALF_FIELD."""
    focal = SIZE / 2 * VIRTUAL_DISTANCE / HALF_FIELD
    K = np.array([[focal, 0.0, (SIZE - 1) / 2], [0.0, focal, (SIZE - 1) / 2], [0.0, 0.0, 1.0]])
    cam_from_world = look_at(pelvis + VIRTUAL_DISTANCE * reach * away, pelvis, tuple(down))
    return Camera("virtual", K, np.zeros(5), cam_from_world, SIZE, SIZE)


def outline_band(inside: np.ndarray, band: int = BAND) -> np.ndarray:
    """(H, W) bool: the pixels within ``band`` pixels (chessboard distance) of a pixel of the other side of the
    outline of ``inside`` (H, W) bool, i.e. its dilation by a (2 band + 1)^2 square minus its erosion by it."""
    kernel = np.ones((2 * band + 1, 2 * band + 1), np.uint8)
    mask = inside.astype(np.uint8)
    return cv2.dilate(mask, kernel).astype(bool) & ~cv2.erode(mask, kernel, borderValue=0).astype(bool)


def random_view(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A uniformly random direction ``away`` (3,) and an image-down ``down`` (3,) square to it, at a random roll."""
    away, roll = rng.normal(size=3), rng.normal(size=3)
    away /= np.linalg.norm(away)
    down = np.cross(away, roll)
    return away, down / np.linalg.norm(down)


def outline_rays(pose_bodies, frame_count: int, faces: np.ndarray, seed: int, views: int = VIEWS) -> OutlineRays:
    """The bank of outline rays over ``views`` virtual cameras (module docstring).

    Args:
        pose_bodies: callable taking a list of training-frame indices and returning their posed bodies
            (``PosedBody``: ``vertices`` (F, V, 3), ``world_from_part`` (F, P, 4, 4), ``reach`` (F,)).
        frame_count: the number of training frames. faces: (T, 3) the body mesh's triangles.
        seed: the draws' seed (the fit's, so a resumed fit draws the same bank). views: virtual cameras.

    Returns:
        OutlineRays on the CPU, float32, ``frames`` indexing the training frames.
    """
    rng = np.random.default_rng(seed)
    picks = np.sort(rng.integers(0, frame_count, size=views))
    origins, dirs, frames, inside = [], [], [], []
    for start in range(0, views, CHUNK):
        chunk = picks[start : start + CHUNK]
        unique = sorted(set(chunk.tolist()))
        bodies = pose_bodies(unique)
        for frame in chunk.tolist():
            i = unique.index(frame)
            pelvis = bodies.world_from_part[i, 0, :3, 3].double().numpy()
            camera = virtual_camera(pelvis, float(bodies.reach[i]), *random_view(rng))
            vertices = bodies.vertices[i].double().numpy()
            v, u = np.nonzero(outline_band(silhouette(camera, vertices, faces)))
            keep = rng.choice(len(u), size=min(RAYS_PER_VIEW, len(u)), replace=False)
            pixels = torch.as_tensor(np.stack([u[keep], v[keep]], axis=1), dtype=torch.float64)
            o, d = rays_from_pixels(torch.as_tensor(camera.K), torch.as_tensor(camera.cam_from_world), pixels)
            # the label from the mesh itself: the rasteriser also draws the pixels its polygons' edges touch
            mesh = trimesh.Trimesh(vertices, faces, process=False)
            inside.append(mesh.ray.intersects_any(o.numpy(), d.numpy()))
            origins.append(o), dirs.append(d), frames.append(np.full(len(keep), frame))
    return OutlineRays(
        torch.cat(origins).float(),
        torch.cat(dirs).float(),
        torch.as_tensor(np.concatenate(frames), dtype=torch.long),
        torch.as_tensor(np.concatenate(inside), dtype=torch.float32),
    )
