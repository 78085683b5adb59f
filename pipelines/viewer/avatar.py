"""What ``narf-view`` renders: the pose of one tab (a capture frame, a motion frame, hand edits, bone lengths) and its
camera, turned into the field's inputs (docs/guides/viewer.md).

Cameras follow OpenCV (x right, y down, z forward), as viser's do: viser reports a camera as ``R_world_camera``
(quaternion w, x, y, z) and its position, with a vertical field of view; the renderer takes ``K`` and
``cam_from_world``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from narf.kinematics import SMPL_PARENTS, rigid_from_rotvec_translation
from pipelines.body.model import BodyModel, pose_batch, posed_from_rest_joints
from pipelines.datasets.camera_path import intrinsics
from pipelines.datasets.zju_mocap import Camera, SmplParams

#: Bone-length groups (NARF's bone edits, docs/model.md §1): the joints whose offsets from their parents scale.
BONE_GROUPS: dict[str, tuple[int, ...]] = {
    "legs": (4, 5, 7, 8, 10, 11),
    "arms": (18, 19, 20, 21, 22, 23),
    "spine": (3, 6, 9),
    "neck and head": (12, 15),
}


@dataclass
class AvatarPose:
    """One tab's pose: ZJU parameters (the frame shown, with any hand edits) and bone-length factors per group."""

    params: SmplParams
    bone_scales: dict[str, float] = field(default_factory=lambda: dict.fromkeys(BONE_GROUPS, 1.0))

    def rest_joints(self, body_model: BodyModel) -> torch.Tensor:
        """(1, 24, 3) the subject's rest joints with each group's offsets from their parents scaled (children
        follow their parents)."""
        rest = body_model.rest_joints(torch.as_tensor(self.params.shapes, dtype=body_model.dtype)[None])
        scale = np.ones(24)
        for name, joints in BONE_GROUPS.items():
            scale[list(joints)] = self.bone_scales.get(name, 1.0)
        out = rest.clone()
        for j in range(1, 24):
            parent = SMPL_PARENTS[j]
            out[:, j] = out[:, parent] + float(scale[j]) * (rest[:, j] - rest[:, parent])
        return out

    def world_from_joint(self, body_model: BodyModel) -> torch.Tensor:
        """(24, 4, 4) the posed joints (chained rotation, origin at the joint)."""
        poses, rh, th = (
            torch.as_tensor(v, dtype=body_model.dtype)[None]
            for v in (self.params.poses, self.params.rh, self.params.th)
        )
        with torch.no_grad():
            body = posed_from_rest_joints(poses, rigid_from_rotvec_translation(rh, th), self.rest_joints(body_model))
        return body.world_from_joint[0]

    def pose_batch(self, body_model: BodyModel):
        """The field's one-frame PoseBatch."""
        poses, rh, th = (
            torch.as_tensor(v, dtype=body_model.dtype)[None]
            for v in (self.params.poses, self.params.rh, self.params.th)
        )
        with torch.no_grad():
            body = posed_from_rest_joints(poses, rigid_from_rotvec_translation(rh, th), self.rest_joints(body_model))
        return pose_batch(body)

    def rotate_joint(self, body_model: BodyModel, joint: int, world_rotation: np.ndarray) -> None:
        """Give ``joint`` the global rotation ``world_rotation`` (3, 3), keeping its parent's: the local rotation
        becomes ``R_parent^T R`` (for the pelvis, the parent is the global ``R(Rh)``)."""
        if joint == 0:
            parent = Rotation.from_rotvec(self.params.rh).as_matrix()
        else:
            parent = self.world_from_joint(body_model)[SMPL_PARENTS[joint], :3, :3].double().numpy()
        local = Rotation.from_matrix(parent.T @ world_rotation).as_rotvec()
        poses = np.array(self.params.poses, dtype=np.float64)
        poses[3 * joint : 3 * joint + 3] = local
        self.params = replace(self.params, poses=poses.astype(self.params.poses.dtype))


def camera_from_viewer(position, wxyz, fov_y: float, aspect: float, long_side: int) -> Camera:
    """A pinhole Camera from viser's camera state: ``R_world_camera`` = quaternion ``wxyz``, centre ``position``,
    vertical field of view ``fov_y`` (radians), ``aspect`` = width / height, the longer image side ``long_side``."""
    if aspect >= 1:
        width, height = long_side, max(16, int(round(long_side / aspect)))
    else:
        width, height = max(16, int(round(long_side * aspect))), long_side
    w, x, y, z = wxyz
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    world_from_cam[:3, 3] = position
    K = intrinsics(width, height, np.degrees(fov_y))
    return Camera("view", K, np.zeros(5), np.linalg.inv(world_from_cam), width, height)


def viewer_from_camera(camera: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """position (3,), wxyz (4,) and vertical field of view (radians) of a capture camera, for viser."""
    rotation = camera.cam_from_world[:3, :3].T
    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    return camera.centre, np.array([w, x, y, z]), float(2 * np.arctan(0.5 * camera.height / camera.K[1, 1]))


def z_depth(depth: np.ndarray, mask: np.ndarray, K: np.ndarray, far: float = 100.0) -> np.ndarray:
    """Distance along the ray (H, W) -> depth along the optical axis, what a rasteriser's depth buffer holds:
    z = t / |K^-1 (u, v, 1)| for unit ray directions; ``far`` where nothing was rendered (mask < 0.5)."""
    height, width = depth.shape
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    z = depth / np.sqrt(x * x + y * y + 1)
    return np.where(mask >= 0.5, z, far).astype(np.float32)
