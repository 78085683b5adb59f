"""Camera rays and the analytic ray-vs-part-box bounds (docs/model.md §5, Project decision b)."""

from __future__ import annotations

import torch

from narf.geometry import check_shape


def rays_from_pixels(
    K: torch.Tensor, cam_from_world: torch.Tensor, pixels: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays through pixel coordinates of an undistorted pinhole camera (pixel centres at integers).

    Args:
        K: (3, 3) intrinsics. cam_from_world: (4, 4). pixels: (N, 2) (u, v).

    Returns:
        origins (N, 3) (the camera centre), unit directions (N, 3).
    """
    check_shape("K", K, (3, 3))
    check_shape("cam_from_world", cam_from_world, (4, 4))
    check_shape("pixels", pixels, (-1, 2))
    homogeneous = torch.cat([pixels, torch.ones_like(pixels[:, :1])], dim=1)
    dirs_cam = homogeneous @ torch.linalg.inv(K).T
    rotation = cam_from_world[:3, :3]
    dirs = dirs_cam @ rotation  # R^T d for row vectors
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    origin = -rotation.T @ cam_from_world[:3, 3]
    return origin.expand_as(dirs), dirs


def image_pixels(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(H*W, 2) pixel coordinates (u, v) in row-major order."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype), torch.arange(width, device=device, dtype=dtype), indexing="ij"
    )
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=1)


def ray_box_slabs(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    world_from_part: torch.Tensor,
    reach: torch.Tensor,
    centres: torch.Tensor,
    half_extents: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Slab test against every part box (oriented in the world, body units), per part.

    In box space o' = (R_i^T (o - t_i)/s - c_i) / h_i, d' = (R_i^T d / s) / h_i, so the box point at depth t is
    u = o' + t d'; per axis t spans (+-1 - o')/d'; t_in = max of the lower ends, t_out = min of the upper ends; the
    ray hits box i if t_in < t_out and t_out > 0.

    Args:
        origins, dirs: (R, 3) rays. world_from_part: (R, P, 4, 4). reach: (R,). centres, half_extents: (P, 3).

    Returns:
        o' (R, P, 3), d' (R, P, 3), t_in (R, P), t_out (R, P), hits (R, P) bool.
    """
    check_shape("origins", origins, (-1, 3))
    n_rays = origins.shape[0]
    check_shape("dirs", dirs, (n_rays, 3))
    check_shape("world_from_part", world_from_part, (n_rays, -1, 4, 4))
    rotation, translation = world_from_part[..., :3, :3], world_from_part[..., :3, 3]
    scale = reach[:, None, None]
    o_box = (torch.einsum("rpji,rpj->rpi", rotation, origins[:, None] - translation) / scale - centres) / half_extents
    d_box = torch.einsum("rpji,rj->rpi", rotation, dirs) / scale / half_extents
    safe = torch.where(d_box.abs() < 1e-12, torch.full_like(d_box, 1e-12) * torch.where(d_box < 0, -1.0, 1.0), d_box)
    t_a, t_b = (-1 - o_box) / safe, (1 - o_box) / safe
    t_low, t_high = torch.minimum(t_a, t_b), torch.maximum(t_a, t_b)
    t_in, t_out = t_low.amax(dim=-1), t_high.amin(dim=-1)
    return o_box, d_box, t_in, t_out, (t_in < t_out) & (t_out > 0)


def ray_box_intersect(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    world_from_part: torch.Tensor,
    reach: torch.Tensor,
    centres: torch.Tensor,
    half_extents: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bounds of the union of the part boxes (:func:`ray_box_slabs`): near = max(0, min t_in), far = max t_out over
    the boxes hit.

    Args:
        origins, dirs: (R, 3) rays. world_from_part: (R, P, 4, 4). reach: (R,). centres, half_extents: (P, 3).

    Returns:
        near (R,), far (R,), hit (R,) bool (near/far are 0 where no box is hit).
    """
    _, _, t_in, t_out, hits = ray_box_slabs(origins, dirs, world_from_part, reach, centres, half_extents)
    return union_bounds(t_in, t_out, hits)


def union_bounds(t_in: torch.Tensor, t_out: torch.Tensor, hits: torch.Tensor):
    """near (R,), far (R,), hit (R,) of per-box intervals (R, P) (see :func:`ray_box_intersect`)."""
    inf = torch.full_like(t_in, float("inf"))
    near = torch.where(hits, t_in, inf).amin(dim=-1).clamp_min(0)
    far = torch.where(hits, t_out, -inf).amax(dim=-1)
    hit = hits.any(dim=-1)
    return torch.where(hit, near, torch.zeros_like(near)), torch.where(hit, far, torch.zeros_like(far)), hit
