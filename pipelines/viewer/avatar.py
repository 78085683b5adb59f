"""What ``narf-view`` renders: the pose of one tab (a capture frame, a motion frame, hand edits, bone lengths) and its
camera, turned into the field's inputs (docs/guides/viewer.md).

Cameras follow OpenCV (x right, y down, z forward), as viser's do: viser reports a camera as ``R_world_camera``
(quaternion w, x, y, z) and its position, with a vertical field of view; the renderer takes ``K`` and
``cam_from_world``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from narf.kinematics import SMPL_PARENTS, rest_offsets_from_world, rigid_from_rotvec_translation, world_from_joints
from pipelines.body.model import pose_batch_from_joints
from pipelines.datasets.camera import Camera
from pipelines.datasets.camera_path import intrinsics
from pipelines.datasets.zju_mocap import SmplParams

#: Bone-length groups (NARF's bone edits, docs/model.md §1): the joints whose offsets from their parents scale.
BONE_GROUPS: dict[str, tuple[int, ...]] = {
    "legs": (4, 5, 7, 8, 10, 11),
    "arms": (18, 19, 20, 21, 22, 23),
    "spine": (3, 6, 9),
    "neck and head": (12, 15),
}


@dataclass
class AvatarPose:
    """One tab's pose as forward kinematics over a rest skeleton (``narf.kinematics.world_from_joints``):
    ``G_0 = world_from_smpl [R(r_0) | J_0]``, ``G_j = G_par(j) [R(r_j) | s_j (J_j - J_par(j))]``.

    Attributes:
        rotvecs: (24, 3) local axis-angle rotations r_j (SMPL ``poses`` reshaped; hand edits change them).
        world_from_smpl: (4, 4) the global transform (ZJU ``[R(Rh) | Th]``).
        rest: (24, 3) rest joints J_j of the skeleton (the subject's shape, or a person's recovered skeleton).
        bone_scales: factor s per bone group (:data:`BONE_GROUPS`; 1 elsewhere).
    """

    rotvecs: np.ndarray
    world_from_smpl: np.ndarray
    rest: np.ndarray
    bone_scales: dict[str, float] = field(default_factory=lambda: dict.fromkeys(BONE_GROUPS, 1.0))

    @classmethod
    def from_params(cls, params: SmplParams, rest: np.ndarray) -> AvatarPose:
        """A ZJU frame on the rest joints of its shapes (``BodyModel.rest_joints``)."""
        world = rigid_from_rotvec_translation(
            torch.as_tensor(params.rh[None], dtype=torch.float64), torch.as_tensor(params.th[None], dtype=torch.float64)
        )
        return cls(np.asarray(params.poses, np.float64).reshape(24, 3), world[0].numpy(), np.asarray(rest, np.float64))

    @classmethod
    def from_joints(cls, world_from_joint: np.ndarray, rest: np.ndarray | None = None) -> AvatarPose:
        """Posed joint frames (24, 4, 4) (THUman / SURREAL poses): local rotations ``R_par^T R_j``, the root's in the
        world; on ``rest`` (24, 3), or the skeleton recovered from the frames (``rest_offsets_from_world``)."""
        frames = np.asarray(world_from_joint, np.float64)
        rotations = frames[:, :3, :3].copy()
        for j in range(1, 24):
            rotations[j] = frames[SMPL_PARENTS[j], :3, :3].T @ frames[j, :3, :3]
        if rest is None:
            rest = rest_offsets_from_world(torch.as_tensor(frames)).numpy()
        world = np.eye(4)
        world[:3, 3] = frames[0, :3, 3] - rest[0]
        return cls(Rotation.from_matrix(rotations).as_rotvec(), world, np.asarray(rest, np.float64))

    def scaled_rest(self) -> np.ndarray:
        """(24, 3) the rest joints with each group's offsets from their parents scaled (children follow)."""
        scale = np.ones(24)
        for name, joints in BONE_GROUPS.items():
            scale[list(joints)] = self.bone_scales.get(name, 1.0)
        out = self.rest.copy()
        for j in range(1, 24):
            parent = SMPL_PARENTS[j]
            out[j] = out[parent] + scale[j] * (self.rest[j] - self.rest[parent])
        return out

    def world_from_joint(self) -> np.ndarray:
        """(24, 4, 4) float64 posed joints (chained rotation, origin at the joint)."""
        rotvecs, rest = torch.as_tensor(self.rotvecs[None]), torch.as_tensor(self.scaled_rest()[None])
        return world_from_joints(rotvecs, rest, torch.as_tensor(self.world_from_smpl[None]))[0].numpy()

    def pose_batch(self):
        """The field's one-frame PoseBatch (float32)."""
        return pose_batch_from_joints(torch.as_tensor(self.world_from_joint()[None])).to(torch.float32)

    def rotate_joint(self, joint: int, world_rotation: np.ndarray) -> None:
        """Give ``joint`` the global rotation ``world_rotation`` (3, 3), keeping its parent's: the local rotation
        becomes ``R_parent^T R`` (for the root, the parent is the global transform's rotation)."""
        if joint == 0:
            parent = self.world_from_smpl[:3, :3]
        else:
            parent = self.world_from_joint()[SMPL_PARENTS[joint], :3, :3]
        self.rotvecs = self.rotvecs.copy()
        self.rotvecs[joint] = Rotation.from_matrix(parent.T @ world_rotation).as_rotvec()


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
