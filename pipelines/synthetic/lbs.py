"""animatable_nerf's ``lbs/`` folder for a capture (docs/formats.md §1.9), written with ``narf-synth --lbs``.

As upstream's ``prepare_blend_weights`` / ``prepare_lbs_meta``: grids span their vertex set's min/max +- 0.05 m
with 0.025 m steps taken by ``np.arange(low, high + 0.025, 0.025)`` (so the last sample lies at or past ``high``),
``indexing='ij'``, 25 channels. The canonical grids (``tbw``, ``bigpose_bw``) hold the weights interpolated at the
closest surface point (barycentric) and the distance to it; the per-frame grids (``bweights/``) hold the nearest
vertex's weights and the distance to that vertex, in the SMPL (posed) frame ``x = R(Rh)^T (v_world - Th)``.
``tvertices`` is the first frame un-posed by inverse LBS (its pose correctives stay in), and ``bigpose_vertices``
is plain LBS of ``tvertices`` into the big pose, without pose correctives.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree
from smplx.lbs import batch_rigid_transform, batch_rodrigues

from fitting.files import write_npy
from fitting.mesh import closest_surface_points
from narf.kinematics import rigid_from_rotvec_translation
from pipelines.body.model import BodyModel
from pipelines.datasets.zju_mocap import SmplParams

BOX_PADDING = 0.05
VOXEL = 0.025


def grid_points(vertices: np.ndarray) -> np.ndarray:
    """(X, Y, Z, 3) sample points over the vertices' bounds +- BOX_PADDING, spaced VOXEL, as upstream."""
    low, high = vertices.min(0) - BOX_PADDING, vertices.max(0) + BOX_PADDING
    axes = [np.arange(low[d], high[d] + VOXEL, VOXEL) for d in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def weight_grid(vertices: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(X, Y, Z, 25) float32 per-frame grid: the nearest vertex's weights and the distance to that vertex."""
    points = grid_points(vertices)
    distance, nearest = cKDTree(vertices).query(points.reshape(-1, 3))
    grid = np.concatenate([weights[nearest], distance[:, None]], axis=1).astype(np.float32)
    return grid.reshape(*points.shape[:3], 25)


def surface_weight_grid(vertices: np.ndarray, faces: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(X, Y, Z, 25) float32 canonical grid: weights interpolated (barycentric) at the closest surface point, and
    the distance to that point."""
    points = grid_points(vertices)
    closest, distance, triangle = closest_surface_points(vertices, faces, points.reshape(-1, 3))
    corners = faces[triangle]
    bary = trimesh.triangles.points_to_barycentric(vertices[corners], closest)
    blended = np.einsum("nk,nkj->nj", bary, weights[corners])
    grid = np.concatenate([blended, distance[:, None]], axis=1).astype(np.float32)
    return grid.reshape(*points.shape[:3], 25)


def skinning_transforms(body: BodyModel, poses: np.ndarray, shapes: np.ndarray) -> np.ndarray:
    """(24, 4, 4) float64 LBS transforms A of one pose (smplx's ``rel_transforms``; upstream's
    ``get_rigid_transformation``)."""
    rest = body.rest_joints(torch.as_tensor(shapes, dtype=body.dtype)[None]).double()
    rotations = batch_rodrigues(torch.as_tensor(poses, dtype=torch.float64).reshape(24, 3))[None]
    _, transforms = batch_rigid_transform(rotations, rest, body.smpl.parents)
    return transforms[0].numpy()


def _blend(weights: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Per-vertex transforms sum_j w_vj A_j: (V, 24), (24, 4, 4) -> (V, 4, 4)."""
    return np.einsum("vj,jab->vab", weights, transforms)


def unpose(points: np.ndarray, weights: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Inverse LBS: x_rest = (sum_j w_j A_j)^-1 x for each vertex, (V, 3)."""
    per_vertex = _blend(weights, transforms)
    return np.einsum("vab,vb->va", np.linalg.inv(per_vertex[:, :3, :3]), points - per_vertex[:, :3, 3])


def repose(points: np.ndarray, weights: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Plain LBS without pose correctives: x = (sum_j w_j A_j) x_rest, (V, 3)."""
    per_vertex = _blend(weights, transforms)
    return np.einsum("vab,vb->va", per_vertex[:, :3, :3], points) + per_vertex[:, :3, 3]


def _smpl_frame(vertices_world: np.ndarray, params: SmplParams) -> np.ndarray:
    """World vertices into the posed SMPL frame, R(Rh)^T (v - Th) (row vectors)."""
    rot = rigid_from_rotvec_translation(torch.as_tensor(params.rh)[None], torch.zeros(1, 3))[0, :3, :3].numpy()
    return (vertices_world - params.th) @ rot


def write_lbs(
    root: Path, body: BodyModel, params: list[SmplParams], vertices_world: np.ndarray, param_indices: list[int]
) -> None:
    """Write ``root/lbs``: joints, parents, weights, faces, tvertices, bigpose_vertices, tbw, bigpose_bw,
    bweights/{i}.npy (one per frame, named like the params files) and smpl_params.npy."""
    out = Path(root) / "lbs"
    (out / "bweights").mkdir(parents=True, exist_ok=True)
    weights = body.skinning_weights.numpy().astype(np.float64)
    shapes = params[0].shapes
    first = _smpl_frame(vertices_world[0], params[0]).astype(np.float64)
    tpose = unpose(first, weights, skinning_transforms(body, params[0].poses, shapes))
    big = np.zeros(72)
    big[5], big[8] = np.deg2rad(30), np.deg2rad(-30)  # hips about z (animatable_nerf's big pose)
    bigpose = repose(tpose, weights, skinning_transforms(body, big, shapes))
    parents = body.smpl.parents.numpy().astype(np.int64)
    parents[0] = 4294967295
    write_npy(out / "joints.npy", body.rest_joints(torch.as_tensor(shapes)[None])[0].numpy().astype(np.float32))
    write_npy(out / "parents.npy", parents)
    write_npy(out / "weights.npy", weights.astype(np.float32))
    write_npy(out / "faces.npy", body.faces.astype(np.int64))
    write_npy(out / "tvertices.npy", tpose.astype(np.float32))
    write_npy(out / "bigpose_vertices.npy", bigpose.astype(np.float32))
    write_npy(out / "tbw.npy", surface_weight_grid(tpose, body.faces, weights))
    write_npy(out / "bigpose_bw.npy", surface_weight_grid(bigpose, body.faces, weights))
    for p, verts, index in zip(params, vertices_world, param_indices):
        write_npy(out / "bweights" / f"{index}.npy", weight_grid(_smpl_frame(verts, p), weights))
    stacked = {
        k: np.stack([getattr(p, a) for p in params])
        for k, a in (("poses", "poses"), ("Rh", "rh"), ("Th", "th"), ("shapes", "shapes"))
    }
    write_npy(out / "smpl_params.npy", stacked, allow_pickle=True)
