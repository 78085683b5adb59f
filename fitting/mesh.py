"""Meshes from a fitted field and their distance to a true surface (docs/design.md *Meshes out*).

``extract_mesh`` samples the density over the union of the posed part boxes, fills every closed pocket of empty
space inside the body (``filled_pockets``: the field's density inside the body is never seen by a camera, and a part
held to its shell holds none deep inside, docs/model.md §1; a pocket would become a surface nobody sees), runs
scikit-image's marching cubes, and colours each vertex with the colour branch seen from outside along its normal,
with a part label from the part selector. ``surface_metrics`` compares two meshes: the symmetric surface distance
(mean and 95th percentile over points sampled uniformly on both surfaces) and the normal consistency.

``vertex_normals`` and ``vertex_faces`` compute what trimesh's properties of the same names do, without their
fallback: trimesh wraps its sparse-matrix path in ``except BaseException`` and drops to a slow loop, which also
swallows a Ctrl-C that lands in it (docs/design.md *Ctrl-C*).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy.ndimage import binary_fill_holes
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes
from tqdm import tqdm

from narf.extraction import nearest_part, posed_box_bounds, query_points

#: Default iso-level of the density (1/m): a 7 mm voxel at this density has an opacity of about 0.3.
DEFAULT_LEVEL = 50.0


@dataclass
class ExtractedMesh:
    """vertices (V, 3) world metres; faces (F, 3); colours (V, 3) in [0, 1]; parts (V,) part index."""

    vertices: np.ndarray
    faces: np.ndarray
    colours: np.ndarray
    parts: np.ndarray


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Angle-weighted vertex normals (Thuermer & Wuethrich 1998, as trimesh's ``Trimesh.vertex_normals``).

    n_v = normalize(sum over the faces f around v of angle_f(v) * n_f), n_f the unit face normal; faces with a
    degenerate normal are left out, and a vertex without faces gets the zero vector.

    Args:
        vertices: (V, 3) float.
        faces: (F, 3) int, counter-clockwise seen from outside.

    Returns:
        (V, 3) float64 unit normals.
    """
    triangles = np.asarray(vertices, np.float64)[faces]
    normals, ok = trimesh.triangles.normals(triangles)  # unit normals of the (F_ok,) faces with an area
    angles = trimesh.triangles.angles(triangles[ok])  # (F_ok, 3) corner angles
    corners = np.asarray(faces)[ok].reshape(-1)
    weighted = (angles[..., None] * normals[:, None, :]).reshape(-1, 3)
    summed = np.stack([np.bincount(corners, weighted[:, k], minlength=len(vertices)) for k in range(3)], axis=1)
    length = np.linalg.norm(summed, axis=1, keepdims=True)
    return np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)


def vertex_faces(n_vertices: int, faces: np.ndarray) -> np.ndarray:
    """The faces around each vertex: (F, 3) int -> (V, max degree) face indices, rows padded with -1.

    Each row lists its faces in increasing order (trimesh's ``Trimesh.vertex_faces`` holds the same sets).
    """
    flat = np.asarray(faces).reshape(-1)
    order = np.argsort(flat, kind="stable")  # corners grouped by vertex, faces increasing within a group
    counts = np.bincount(flat, minlength=n_vertices)
    starts = np.cumsum(counts) - counts
    slot = np.arange(len(flat)) - np.repeat(starts, counts)  # position of each sorted corner within its group
    out = np.full((n_vertices, max(int(counts.max(initial=0)), 1)), -1, np.int64)
    out[flat[order], slot] = order // 3
    return out


def density_grid(field, pose, resolution: int, chunk: int = 1 << 16, latent=None, progress: bool = False):
    """The density on a regular grid over the posed part boxes, ``resolution`` samples along the longest side.

    Returns:
        (X, Y, Z) float32 densities, origin (3,) of sample [0, 0, 0] and the spacing (metres).
    """
    if resolution < 8:
        raise ValueError(f"--resolution must be at least 8, got {resolution}")
    device = next(field.parameters()).device
    bounds = posed_box_bounds(pose, field.box_centres, field.box_half_extents).double().cpu().numpy()
    spacing = float((bounds[1] - bounds[0]).max()) / (resolution - 1)
    shape = tuple(int(np.floor((bounds[1, d] - bounds[0, d]) / spacing + 1e-9)) + 1 for d in range(3))
    sigma = np.empty(int(np.prod(shape)), np.float32)
    starts = range(0, sigma.size, chunk)
    for start in tqdm(starts, desc="density grid", unit="chunk", disable=not progress):
        index = np.stack(np.unravel_index(np.arange(start, min(start + chunk, sigma.size)), shape), axis=1)
        points = torch.as_tensor(bounds[0] + index * spacing, dtype=torch.float32, device=device)
        sigma[start : start + len(index)] = query_points(field, points, pose, chunk=chunk, latent=latent)["sigma"].cpu()
    return sigma.reshape(shape), bounds[0], spacing


def filled_pockets(volume: np.ndarray, level: float) -> np.ndarray:
    """``volume`` (X, Y, Z) with every region below ``level`` that no face-connected path below it joins to the
    grid's border raised to twice the level (scipy's ``binary_fill_holes``): no surface around a closed pocket."""
    solid = volume > level
    return np.where(binary_fill_holes(solid) & ~solid, np.float32(2 * level), volume).astype(volume.dtype)


def extract_mesh(
    field, pose, resolution: int = 256, level: float = DEFAULT_LEVEL, latent=None, progress: bool = False
) -> ExtractedMesh:
    """The surface ``sigma = level`` of a field in one frame's pose (module docstring).

    Raises:
        ValueError: the density never reaches ``level`` (an untrained field, or a level above its range).
    """
    volume, origin, spacing = density_grid(field, pose, resolution, latent=latent, progress=progress)
    if not volume.max() > level:
        raise ValueError(f"the density never reaches the level {level:g} (max {volume.max():.3g}); lower --level")
    padded = np.pad(filled_pockets(volume, level), 1)  # zero density outside the grid closes the surface
    verts, faces, _, _ = marching_cubes(padded, level, spacing=(spacing,) * 3)
    verts, faces = verts + origin - spacing, np.ascontiguousarray(faces[:, ::-1])  # wind outward (density inside)
    # angle-weighted face normals of the mesh itself: the grid gradient of a sharp density is a poor normal
    outward = vertex_normals(verts, faces)
    device = next(field.parameters()).device
    points = torch.as_tensor(verts, dtype=torch.float32, device=device)
    looking = -torch.tensor(np.array(outward, dtype=np.float32), device=device)
    out = query_points(field, points, pose, dirs=looking, latent=latent)
    if out["part_probs"] is not None:
        parts = out["part_probs"].argmax(dim=-1)
    else:
        parts = nearest_part(field, points, pose)
    return ExtractedMesh(verts, faces.astype(np.int64), out["rgb"].clamp(0, 1).cpu().numpy(), parts.cpu().numpy())


def closest_surface_points(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, k: int = 3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points on a triangle mesh: (N, 3) points -> closest (N, 3), distance (N,), triangle (N,).

    The candidates of a point are the triangles around its ``k`` nearest vertices: on a well-sampled mesh (a body
    model, a marching-cubes surface) the closest triangle has a corner among the 3 nearest vertices
    (``tests/test_synthetic.py`` checks the result against ``trimesh.proximity.closest_point``, which searches
    every triangle and takes ~5x longer on a body grid).
    """
    _, nearest = cKDTree(vertices).query(points, k=k)
    adjacency = vertex_faces(len(vertices), faces)  # (V, max degree), -1 padded
    candidates = adjacency[nearest].reshape(len(points), -1)  # (N, k * degree)
    valid = candidates >= 0
    safe = np.where(valid, candidates, 0)
    triangles = vertices[faces[safe.reshape(-1)]]
    repeated = np.repeat(points, safe.shape[1], axis=0)
    closest = trimesh.triangles.closest_point(triangles, repeated).reshape(*safe.shape, 3)
    distance = np.where(valid, np.linalg.norm(closest - points[:, None], axis=-1), np.inf)
    best = distance.argmin(axis=1)
    rows = np.arange(len(points))
    return closest[rows, best], distance[rows, best], safe[rows, best]


def surface_metrics(
    predicted: trimesh.Trimesh, truth: trimesh.Trimesh, n_samples: int = 20000, seed: int = 0
) -> dict[str, float]:
    """Symmetric surface distance and normal consistency of two meshes.

    ``n_samples`` points are drawn uniformly (by area) on each surface; each is matched to the closest point of the
    other surface. Distances of both directions are pooled: ``mean_mm`` and ``p95_mm``. Normal consistency is the
    mean |n_a . n_b| between a sample's face normal and the normal of the face it matches (1 = aligned).
    """
    rng = np.random.default_rng(seed)
    distances, cosines = [], []
    for source, target in ((predicted, truth), (truth, predicted)):
        samples, face = trimesh.sample.sample_surface(source, n_samples, seed=int(rng.integers(1 << 31)))
        _, distance, matched = closest_surface_points(np.asarray(target.vertices), np.asarray(target.faces), samples)
        distances.append(distance)
        cosines.append(np.abs(np.einsum("nd,nd->n", source.face_normals[face], target.face_normals[matched])))
    pooled = np.concatenate(distances) * 1000.0
    return {
        "mean_mm": float(pooled.mean()),
        "p95_mm": float(np.percentile(pooled, 95)),
        "normal_consistency": float(np.concatenate(cosines).mean()),
        "predicted_to_true_mean_mm": float(distances[0].mean() * 1000.0),
        "true_to_predicted_mean_mm": float(distances[1].mean() * 1000.0),
    }
