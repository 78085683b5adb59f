"""Rasterised bone maps, the input of the CNN baseline (docs/model.md §4): 46 channels per image.

Channel layout: 0 bone disparity (1/z of the nearest bone under the pixel, 0 elsewhere); 1-19 one map per
part with that part's bones; 20-43 one square per joint; 44-45 pixel coordinates x, y in [-1, 1].
"""

from __future__ import annotations

import torch

from narf.geometry import check_shape
from narf.kinematics import PART_JOINTS, SMPL_PARENTS

N_CHANNELS = 46


def _segment_distance(pixels: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance of pixels (N, 2) to segments a-b (K, 2) and the segment parameter s in [0, 1]: (N, K) each."""
    ab = b - a
    s = (((pixels[:, None] - a[None]) * ab[None]).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)).clamp(0, 1)
    closest = a[None] + s[..., None] * ab[None]
    return (pixels[:, None] - closest).norm(dim=-1), s


def bone_maps(
    cam_from_joint: torch.Tensor, K: torch.Tensor, size: int, thickness: float = 1.5, square: int = 2
) -> torch.Tensor:
    """Rasterise the skeleton of one view.

    Args:
        cam_from_joint: (24, 4, 4) joint transforms in the camera frame (origins = posed joints).
        K: (3, 3) intrinsics at ``size`` x ``size`` (pixel centres at integers).
        size: image side.
        thickness: bone half-width in pixels.
        square: joint square half-size in pixels.

    Returns:
        (46, size, size) float maps.
    """
    check_shape("cam_from_joint", cam_from_joint, (24, 4, 4))
    check_shape("K", K, (3, 3))
    dtype, device = cam_from_joint.dtype, cam_from_joint.device
    joints = cam_from_joint[:, :3, 3]
    depth = joints[:, 2].clamp_min(1e-6)
    uv = (joints @ K.T)[:, :2] / depth[:, None]
    ys, xs = torch.meshgrid(
        torch.arange(size, dtype=dtype, device=device), torch.arange(size, dtype=dtype, device=device), indexing="ij"
    )
    pixels = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)
    children = [j for j in range(1, 24)]
    parents = [SMPL_PARENTS[j] for j in children]
    dist, s = _segment_distance(pixels, uv[parents], uv[children])  # (N, 23)
    on_bone = dist <= thickness
    disparity = 1 / (depth[parents][None] * (1 - s) + depth[children][None] * s)
    maps = torch.zeros(N_CHANNELS, size * size, dtype=dtype, device=device)
    maps[0] = torch.where(on_bone, disparity, torch.zeros_like(disparity)).amax(dim=-1)
    for part, joint in enumerate(PART_JOINTS):
        bones = [k for k, parent in enumerate(parents) if parent == joint]
        maps[1 + part] = on_bone[:, bones].any(dim=-1).to(dtype)
    inside = ((pixels[:, None] - uv[None]).abs() <= square).all(dim=-1)  # (N, 24)
    maps[20:44] = inside.T.to(dtype)
    maps[44] = pixels[:, 0] / (size - 1) * 2 - 1
    maps[45] = pixels[:, 1] / (size - 1) * 2 - 1
    return maps.reshape(N_CHANNELS, size, size)


def bone_pose_vector(cam_from_joint: torch.Tensor) -> torch.Tensor:
    """Camera-frame pose of each part (rotation 9 + translation 3): (..., 24, 4, 4) -> (..., 19 * 12)."""
    parts = cam_from_joint[..., list(PART_JOINTS), :3, :]  # (..., 19, 3, 4)
    return torch.cat([parts[..., :3].flatten(-2), parts[..., 3]], dim=-1).flatten(-2)
