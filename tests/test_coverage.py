"""Surfaces the training views saw (docs/model.md §7): the face-index render against trimesh's ray casting, and the
unseen pixels of a sphere that one camera saw, against the cap it sees face-on (by hand)."""

from __future__ import annotations

import cv2
import numpy as np
import trimesh

from pipelines.datasets.camera import Camera, face_ids
from pipelines.runs.subject.coverage import FACE_ON_COS, facing_faces, grown, shown_faces, unseen_pixels

K = np.array([[200.0, 0.0, 80.0], [0.0, 200.0, 60.0], [0.0, 0.0, 1.0]])


def _camera_at(centre: np.ndarray) -> Camera:
    """A 160 x 120 camera at ``centre`` looking at the origin (its y axis as close to world -z or -y as allowed)."""
    forward = -centre / np.linalg.norm(centre)
    up = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    cam_from_world = np.eye(4)
    cam_from_world[:3, :3] = np.stack([right, down, forward])
    cam_from_world[:3, 3] = -cam_from_world[:3, :3] @ centre
    return Camera("c", K, np.zeros(5), cam_from_world, 160, 120)


def _two_spheres() -> trimesh.Trimesh:
    near = trimesh.creation.icosphere(3, radius=0.4)
    far = trimesh.creation.icosphere(3, radius=0.5)
    far.apply_translation([0.3, 0.1, -0.8])  # behind the first one, seen from +z, and partly hidden by it
    return trimesh.util.concatenate([near, far])


def _outline(region: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels within a pixel of the edge of ``region`` (H, W) bool, on either side."""
    square, region = np.ones((3, 3), np.uint8), region.astype(np.uint8)
    return cv2.dilate(region, square).astype(bool) & ~cv2.erode(region, square).astype(bool)


def test_face_ids_against_trimesh_ray_casting():
    """Each pixel centre's ray cast into two spheres, one partly hiding the other (trimesh, exact). Away from the
    outlines (a pixel either side of where the body or the nearer sphere ends: a filled polygon's pixel rule and
    the 1/4-px vertex rounding decide those), the render covers the same pixels, shows the sphere the ray hits
    first, and on it the face the ray hits or one that shares a vertex with it (a filled polygon takes the pixels
    its edges touch, so a pixel on an edge between two faces goes to whichever is drawn last)."""
    mesh = _two_spheres()
    n_near = len(mesh.faces) // 2
    camera = _camera_at(np.array([0.0, 0.0, 3.0]))
    ids = face_ids(camera, mesh.vertices, mesh.faces)
    u, v = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float))
    rays_cam = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1) @ np.linalg.inv(K).T
    directions = rays_cam @ camera.cam_from_world[:3, :3]  # world directions: R^T d for each row
    origins = np.repeat(camera.centre[None], len(directions), 0)
    hit = mesh.ray.intersects_first(origins, directions).reshape(ids.shape)
    truth = hit >= 0
    away = ~_outline(truth) & ~_outline(truth & (hit < n_near))
    assert truth.sum() > 3000 and (truth & (hit >= n_near) & away).sum() > 300  # the far sphere shows
    assert np.array_equal((ids >= 0)[away], truth[away])
    both = away & truth
    assert np.array_equal(ids[both] < n_near, hit[both] < n_near)
    assert all(set(mesh.faces[a]) & set(mesh.faces[b]) for a, b in zip(ids[both], hit[both]))


def _face_on_height(r: float, d: float, min_cos: float) -> float:
    """The height z = r cos(t) above which a sphere's points (radius r, centre at the origin) face a camera at
    distance d on +z within ``min_cos``: the normal (sin t, 0, cos t) against the direction to the camera gives
    cos = (d cos t - r) / sqrt(r^2 + d^2 - 2 r d cos t), which rises with cos t; solved by bisection."""
    low, high = -1.0, 1.0
    for _ in range(60):
        c = (low + high) / 2
        low, high = (c, high) if (d * c - r) / np.sqrt(r * r + d * d - 2 * r * d * c) < min_cos else (low, c)
    return r * (low + high) / 2


def test_unseen_pixels_of_a_sphere_that_one_camera_saw():
    """A sphere of radius r = 0.5 seen by one training camera at distance d = 3 on +z: it sees face-on (within
    ``FACE_ON_COS``) the cap above z0 (:func:`_face_on_height`, 0.31), so every face it counts is centred above
    z0 less a face (an icosphere of 4 subdivisions has faces under 0.05 across), and the grown ring reaches a face
    further. So from the opposite camera everything is unseen; from the training camera itself (whose grazing ring it
    does not count) and from the side, every pixel of a face centred below z0 - 0.1 is unseen and every pixel of one
    centred above z0 + 0.05 is seen: a ring on the disc's edge from the first, most of the disc from the second."""
    mesh = trimesh.creation.icosphere(4, radius=0.5)
    faces, vertices = np.asarray(mesh.faces), np.asarray(mesh.vertices)
    training = _camera_at(np.array([0.0, 0.0, 3.0]))
    ids = face_ids(training, vertices, faces)
    counts = (shown_faces(ids, ids >= 0, len(faces)) & facing_faces(training, vertices, faces, FACE_ON_COS)).astype(
        np.int32
    )
    z0 = _face_on_height(0.5, 3.0, FACE_ON_COS)
    centroid_z = vertices[faces].mean(axis=1)[:, 2]
    assert 0.3 < z0 < 0.32
    seen = grown(faces, counts > 0)  # a face a few pixels across can lose every pixel to its neighbours' edges
    assert (centroid_z[counts > 0] > z0 - 0.05).all() and seen[centroid_z > z0 + 0.05].all()
    assert not seen[centroid_z < z0 - 0.1].any()

    opposite = _camera_at(np.array([0.0, 0.0, -3.0]))
    on_body = face_ids(opposite, vertices, faces) >= 0
    assert np.array_equal(unseen_pixels(opposite, vertices, faces, counts), on_body)
    for camera, share in ((training, (0.05, 0.4)), (_camera_at(np.array([3.0, 0.0, 0.0])), (0.6, 0.95))):
        shown = face_ids(camera, vertices, faces)
        unseen = unseen_pixels(camera, vertices, faces, counts)
        z = np.where(shown >= 0, centroid_z[np.maximum(shown, 0)], np.nan)
        assert unseen[z < z0 - 0.1].all() and not unseen[z > z0 + 0.05].any()
        assert share[0] < unseen.sum() / (shown >= 0).sum() < share[1]  # the training camera's grazing ring
