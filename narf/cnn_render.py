"""Image-space rendering of the CNN baseline (docs/model.md §4): bone maps of a camera and pose at the network's
square size, then RGB and mask resampled to the camera's image size. It has no depth or segmentation; depth is
returned as zeros so that grids and videos keep their layout."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from narf.bone_maps import bone_maps, bone_pose_vector
from narf.fields.common import PoseBatch
from narf.geometry import check_shape


def scaled_intrinsics(K: torch.Tensor, height: int, width: int, size: int) -> torch.Tensor:
    """(..., 3, 3) intrinsics of an image resampled from ``height`` x ``width`` to ``size`` x ``size`` (pixel
    centres at integers: u' = (u + 0.5) size / width - 0.5)."""
    sx, sy = size / width, size / height
    out = K.clone()
    out[..., 0, :] = K[..., 0, :] * sx
    out[..., 1, :] = K[..., 1, :] * sy
    out[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    out[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return out


def cnn_inputs(
    world_from_joint: torch.Tensor, cam_from_world: torch.Tensor, K: torch.Tensor, height: int, width: int, size: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Network inputs of B views: maps (B, 46, size, size) and bone poses (B, 228).

    Args:
        world_from_joint: (B, 24, 4, 4). cam_from_world: (B, 4, 4). K: (B, 3, 3) at ``height`` x ``width``.
    """
    check_shape("world_from_joint", world_from_joint, (-1, 24, 4, 4))
    check_shape("cam_from_world", cam_from_world, (world_from_joint.shape[0], 4, 4))
    cam_from_joint = cam_from_world[:, None] @ world_from_joint
    K_small = scaled_intrinsics(K, height, width, size)
    maps = torch.stack([bone_maps(cam_from_joint[b], K_small[b], size) for b in range(cam_from_joint.shape[0])])
    return maps, bone_pose_vector(cam_from_joint)


def render_cnn_image(
    model,
    K: torch.Tensor,
    cam_from_world: torch.Tensor,
    height: int,
    width: int,
    pose: PoseBatch,
    latent: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """rgb (H, W, 3), mask (H, W) and depth (H, W, zeros) of one camera and a one-frame pose with joints;
    ``latent`` (1, 2 L): an autoencoder's code."""
    if pose.world_from_joint is None:
        raise ValueError("the CNN baseline needs the pose's world_from_joint (all 24 SMPL joints)")
    size = model.image_size
    maps, bones = cnn_inputs(pose.world_from_joint[:1], cam_from_world[None], K[None], height, width, size)
    rgb, mask = model(maps, bones, latent)
    rgb = F.interpolate(rgb, size=(height, width), mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
    mask = F.interpolate(mask[:, None], size=(height, width), mode="bilinear", align_corners=False)[0, 0]
    return {"rgb": rgb.clamp(0, 1), "mask": mask.clamp(0, 1), "depth": torch.zeros_like(mask)}
