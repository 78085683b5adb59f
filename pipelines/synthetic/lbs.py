"""animatable_nerf's ``lbs/`` folder for a capture (docs/formats.md §1.9), written with ``narf-synth --lbs``.

Grids span their vertex set's min/max +- 0.05 m with 0.025 m voxels (``indexing='ij'``) and hold 25 channels:
the 24 blend weights of the nearest vertex and the distance to it (the nearest vertex stands in for the nearest
surface point). Per-frame grids are in the SMPL (posed) frame, ``x = R(Rh)^T (v_world - Th)``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from smplx.lbs import lbs

from narf.kinematics import rigid_from_rotvec_translation
from pipelines.body.model import BodyModel
from pipelines.datasets.zju_mocap import SmplParams

BOX_PADDING = 0.05
VOXEL = 0.025


def weight_grid(vertices: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(X, Y, Z, 25) float32 grid over the vertices' padded bounds: nearest-vertex weights and distance."""
    low, high = vertices.min(0) - BOX_PADDING, vertices.max(0) + BOX_PADDING
    axes = [np.arange(low[d], high[d] + 1e-9, VOXEL) for d in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    distance, nearest = cKDTree(vertices).query(points.reshape(-1, 3))
    grid = np.concatenate([weights[nearest], distance[:, None]], axis=1).astype(np.float32)
    return grid.reshape(*points.shape[:3], 25)


def _posed_smpl_frame(body: BodyModel, poses: np.ndarray, shapes: np.ndarray) -> np.ndarray:
    smpl = body.smpl
    with torch.no_grad():
        verts, _ = lbs(
            torch.as_tensor(shapes, dtype=body.dtype)[None],
            torch.as_tensor(poses, dtype=body.dtype)[None],
            smpl.v_template,
            smpl.shapedirs,
            smpl.posedirs,
            smpl.J_regressor,
            smpl.parents,
            smpl.lbs_weights,
        )
    return verts[0].numpy()


def write_lbs(
    root: Path, body: BodyModel, params: list[SmplParams], vertices_world: np.ndarray, param_indices: list[int]
) -> None:
    """Write ``root/lbs``: joints, parents, weights, faces, tvertices, bigpose_vertices, tbw, bigpose_bw,
    bweights/{i}.npy (one per frame, named like the params files) and smpl_params.npy."""
    out = Path(root) / "lbs"
    (out / "bweights").mkdir(parents=True, exist_ok=True)
    weights = body.skinning_weights.numpy().astype(np.float32)
    shapes = params[0].shapes
    tpose = _posed_smpl_frame(body, np.zeros(72, np.float32), shapes)
    big = np.zeros(72, np.float32)
    big[5], big[8] = np.deg2rad(30), np.deg2rad(-30)  # hips about z (animatable_nerf's big pose)
    bigpose = _posed_smpl_frame(body, big, shapes)
    parents = body.smpl.parents.numpy().astype(np.int64)
    parents[0] = 4294967295
    np.save(out / "joints.npy", body.rest_joints(torch.as_tensor(shapes)[None])[0].numpy().astype(np.float32))
    np.save(out / "parents.npy", parents)
    np.save(out / "weights.npy", weights)
    np.save(out / "faces.npy", body.faces.astype(np.int64))
    np.save(out / "tvertices.npy", tpose.astype(np.float32))
    np.save(out / "bigpose_vertices.npy", bigpose.astype(np.float32))
    np.save(out / "tbw.npy", weight_grid(tpose, weights))
    np.save(out / "bigpose_bw.npy", weight_grid(bigpose, weights))
    for p, verts, index in zip(params, vertices_world, param_indices):
        rot = rigid_from_rotvec_translation(torch.as_tensor(p.rh)[None], torch.zeros(1, 3))[0, :3, :3].numpy()
        smpl_frame = (verts - p.th) @ rot  # R^T (v - Th) for row vectors
        np.save(out / "bweights" / f"{index}.npy", weight_grid(smpl_frame, weights))
    stacked = {
        k: np.stack([getattr(p, a) for p in params])
        for k, a in (("poses", "poses"), ("Rh", "rh"), ("Th", "th"), ("shapes", "shapes"))
    }
    np.save(out / "smpl_params.npy", stacked, allow_pickle=True)
