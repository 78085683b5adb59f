"""The density level of a fit's surface, chosen from the fit itself (docs/design.md *Meshes out*).

A density field has no surface of its own: marching cubes needs an iso-level, and the density scale of a fit depends
on how long it trained (a one-minute fit may peak below 10 m^-1, a long one above 1,000). The level is chosen as the
one whose silhouette best matches the masks of the fit's own training views, never evaluation data:

* the density is sampled on a grid over the posed part boxes of a training frame (:func:`fitting.mesh.density_grid`);
* each pixel of a training camera gets the largest trilinear density along its ray (:func:`max_density_image`), so
  the pixel lies inside the silhouette of the surface ``sigma = l`` exactly when that maximum exceeds ``l``;
* for candidate levels spaced geometrically below the peak density, the intersection-over-union of those silhouettes
  with the masks is pooled over all views (pixels of the masks' boundary band left out), and the best level wins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from fitting.mesh import density_grid
from narf.rays import image_pixels, rays_from_pixels


@dataclass
class LevelView:
    """One training view: camera (undistorted, at the mask's size) and its mask.

    Attributes:
        K: (3, 3) intrinsics. cam_from_world: (4, 4) extrinsics (metres).
        mask: (H, W) bool person mask. ignore: (H, W) bool pixels left out (the mask's boundary band).
    """

    K: np.ndarray
    cam_from_world: np.ndarray
    mask: np.ndarray
    ignore: np.ndarray


@dataclass
class LevelChoice:
    """The chosen level, its pooled IoU, and every candidate's (for the report)."""

    level: float
    iou: float
    levels: np.ndarray
    ious: np.ndarray
    n_views: int


def max_density_image(
    volume: np.ndarray, origin: np.ndarray, spacing: float, K: np.ndarray, cam_from_world: np.ndarray, shape, stride=1
) -> np.ndarray:
    """The largest density along each pixel's ray through a density grid.

    Sample ``[i, j, k]`` of ``volume`` lies at ``origin + (i, j, k) * spacing``. A ray is sampled between its entry
    and exit of the grid's box every half voxel or closer, with trilinear interpolation (zero outside the grid).

    Args:
        volume: (X, Y, Z) densities. origin: (3,) metres. K, cam_from_world: (3, 3), (4, 4) undistorted camera.
        shape: (H, W) of the image. stride: every ``stride``-th pixel in each direction.

    Returns:
        (ceil(H / stride), ceil(W / stride)) float32.
    """
    height, width = shape
    out_shape = (-(-height // stride), -(-width // stride))
    pixels = image_pixels(*out_shape, dtype=torch.float64) * stride  # every stride-th pixel, row-major
    K64, extrinsics = (torch.as_tensor(m, dtype=torch.float64) for m in (K, cam_from_world))
    origins, dirs = rays_from_pixels(K64, extrinsics, pixels)
    size = torch.tensor(volume.shape, dtype=torch.float64)
    low = torch.as_tensor(origin, dtype=torch.float64)
    high = low + (size - 1) * spacing
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t_a, t_b = (low - origins) / safe, (high - origins) / safe
    t_in = torch.minimum(t_a, t_b).amax(dim=1).clamp_min(0)
    t_out = torch.maximum(t_a, t_b).amin(dim=1)
    hit = (t_out > t_in).nonzero()[:, 0]
    result = torch.zeros(origins.shape[0], dtype=torch.float32)
    grid_volume = torch.as_tensor(volume, dtype=torch.float32)[None, None]  # (1, 1, X, Y, Z) read as (D, H, W)
    n_samples = int(np.ceil(float(torch.linalg.norm(high - low)) / (0.5 * spacing))) + 1
    steps = torch.linspace(0, 1, n_samples, dtype=torch.float64)
    chunk = max(1, (1 << 22) // n_samples)
    for start in range(0, hit.numel(), chunk):
        ids = hit[start : start + chunk]
        t = t_in[ids, None] + (t_out[ids] - t_in[ids])[:, None] * steps  # (R, S)
        points = origins[ids, None] + t[..., None] * dirs[ids, None]  # (R, S, 3)
        normalised = 2 * (points - low) / (high - low) - 1  # [-1, 1] across the grid, x indexing X
        grid = normalised.flip(-1).float()[None, None]  # grid_sample wants (w, h, d) = (z, y, x)
        sampled = F.grid_sample(grid_volume, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        result[ids] = sampled[0, 0, 0].amax(dim=-1)
    return result.reshape(out_shape).numpy()


def candidate_levels(peak: float, count: int = 64) -> np.ndarray:
    """``count`` levels spaced geometrically from peak / 1000 to 0.9 peak (the level must be below the peak)."""
    if not np.isfinite(peak) or peak <= 0:
        raise ValueError(f"the fit's density is nowhere positive (peak {peak:g}): no surface to extract")
    return np.geomspace(peak * 1e-3, peak * 0.9, count)


def silhouette_ious(max_densities: list[np.ndarray], views: list[LevelView], levels: np.ndarray, stride: int = 1):
    """IoU of the silhouettes ``max density > level`` with the masks, pooled over views: (L,) float64.

    IoU(l) = sum_v |S_v(l) & M_v| / sum_v |S_v(l) | M_v| over the pixels not ignored.
    """
    inter, union = np.zeros(len(levels)), np.zeros(len(levels))
    for image, view in zip(max_densities, views, strict=True):
        mask, keep = view.mask[::stride, ::stride], ~view.ignore[::stride, ::stride]
        if mask.shape != image.shape:
            raise ValueError(f"a mask sampled every {stride} pixels is {mask.shape}, its silhouette {image.shape}")
        values, inside = image[keep], mask[keep]
        above = values[None, :] > levels[:, None]  # (L, N)
        inter += (above & inside[None]).sum(axis=1)
        union += (above | inside[None]).sum(axis=1)
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def choose_level(field, frames: list, resolution: int = 128, stride: int = 2, latent=None) -> LevelChoice:
    """The level whose silhouettes best match the training masks (module docstring).

    Args:
        field: a fitted Field. frames: ``(pose, views)`` pairs, a one-frame PoseBatch and its LevelViews.
        resolution: grid samples along the longest side. stride: pixel stride of the silhouettes.

    Raises:
        ValueError: no views, or a field whose density is nowhere positive.
    """
    if not any(views for _, views in frames):
        raise ValueError("choosing a mesh level needs at least one training view")
    images, all_views = [], []
    for pose, views in frames:
        volume, origin, spacing = density_grid(field, pose, resolution, latent=latent)
        for view in views:
            images.append(
                max_density_image(volume, origin, spacing, view.K, view.cam_from_world, view.mask.shape, stride)
            )
            all_views.append(view)
    levels = candidate_levels(float(max(image.max() for image in images)))
    ious = silhouette_ious(images, all_views, levels, stride)
    best = int(np.argmax(ious))
    return LevelChoice(float(levels[best]), float(ious[best]), levels, ious, len(all_views))
