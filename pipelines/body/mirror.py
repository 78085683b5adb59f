"""The mirror image of an SMPL body about its own sagittal plane (docs/model.md §6, *Left-right symmetry*).

SMPL's template is left-right symmetric about the plane x = 0 of its rest frame, and so are its joints up to the
template's own asymmetry (about a centimetre). Reflecting a posed body about the plane through its pelvis that the
root's x axis is normal to gives the body in the mirror-image pose: each joint takes its mirror joint's rotation,
reflected ((x, y, z) -> (x, -y, -z) for an axis-angle vector under the reflection x -> -x), and the root's own
rotation, which carries the plane, stays as it is (and so do Rh, Th and the shape).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipelines.datasets.zju_mocap import SmplParams

#: SMPL's 24 joints: each one's mirror joint (left hip <-> right hip, ...; the spine, neck and head their own)
SMPL_MIRROR = (0, 2, 1, 3, 5, 4, 6, 8, 7, 9, 11, 10, 12, 14, 13, 15, 17, 16, 19, 18, 21, 20, 23, 22)


def mirror_smpl_poses(poses: np.ndarray) -> np.ndarray:
    """(..., 72) axis-angle poses -> their mirror images: joints 1-23 swapped with their mirror joints and reflected,
    theta'_j = S theta_m(j) with S = diag(1, -1, -1); the root (joint 0) kept."""
    joints = np.asarray(poses).reshape(*np.shape(poses)[:-1], 24, 3)
    mirrored = joints[..., list(SMPL_MIRROR), :] * np.array([1.0, -1.0, -1.0], dtype=joints.dtype)
    mirrored[..., 0, :] = joints[..., 0, :]
    return mirrored.reshape(np.shape(poses))


class MirroredSource:
    """A capture (anything with ``params(frame)``) whose bodies stand in their mirror-image poses."""

    def __init__(self, source):
        self.source = source

    def params(self, frame: int) -> SmplParams:
        params = self.source.params(frame)
        return dataclasses.replace(params, poses=mirror_smpl_poses(params.poses))
