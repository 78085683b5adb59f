"""The SMPL body of a SURREAL clip in SURREAL's world (``docs/formats.md §5.4``): the world orientation is
R_x(pi/2) R_z(zrot) R(pose[0:3]) and the pelvis sits at ``joints3D[0]``, so the posed body projects through the
clip's camera onto its segmentation."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from pipelines.body.model import BodyModel, PosedBody
from pipelines.datasets.surreal import SurrealClip

#: R_x(pi/2): SURREAL's turn of the z-up mocap frame into its world (docs/formats.md §5.4).
R_X90 = cv2.Rodrigues(np.array([np.pi / 2, 0.0, 0.0]))[0]


def surreal_world_pose(pose: np.ndarray, zrot: float) -> np.ndarray:
    """(72,) pose whose root is the body's world orientation R_x(pi/2) R_z(zrot) R(pose[0:3])."""
    out = np.asarray(pose, np.float64).copy()
    rz = cv2.Rodrigues(np.array([0.0, 0.0, float(zrot)]))[0]
    world = R_X90 @ rz @ cv2.Rodrigues(out[:3].reshape(3, 1))[0]
    out[:3] = cv2.Rodrigues(world)[0].ravel()
    return out


def pose_surreal(body_model: BodyModel, clip: SurrealClip, frames: list[int]) -> PosedBody:
    """The clip's body at 0-based ``frames`` in SURREAL's world (pelvis at ``joints3D[:, 0]``).

    SURREAL picks the gender's model; the stand-in body is neutral, so the clip's betas drive the shape.
    """
    if not frames or min(frames) < 0 or max(frames) >= clip.n_frames:
        raise ValueError(f"{clip.path}: frames {frames} outside 0..{clip.n_frames - 1}")
    dtype = body_model.dtype
    poses = np.stack([surreal_world_pose(clip.pose[t], clip.zrot[t]) for t in frames])
    betas = torch.as_tensor(clip.shape[frames], dtype=dtype)
    pelvis_rest = body_model.rest_joints(betas)[:, 0]
    transl = torch.as_tensor(clip.joints3d[frames, 0], dtype=dtype) - pelvis_rest
    zeros = torch.zeros(len(frames), 3, dtype=dtype)
    return body_model.pose_zju(torch.as_tensor(poses, dtype=dtype), zeros, transl, betas)
