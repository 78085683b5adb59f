"""Querying a field at arbitrary world points, for surface extraction (docs/design.md *Meshes out*).

Pure torch. The field's forward takes R rays of S samples with one direction per ray; here any (N, 3) points are
cut into rows of ``samples_per_row`` samples that share a direction (density ignores it), or one point per row when
each point has its own viewing direction (colours).
"""

from __future__ import annotations

import itertools

import torch

from narf.fields.common import PoseBatch, part_box_coordinates
from narf.geometry import check_shape


def posed_box_bounds(pose: PoseBatch, centres: torch.Tensor, half_extents: torch.Tensor) -> torch.Tensor:
    """World bounds of the union of the part boxes of one frame: (2, 3) [min; max].

    A box corner u in {-1, 1}^3 of part i lies at x_i = c_i + u h_i in body units, i.e. at R_i (s x_i) + t_i.

    Args:
        pose: PoseBatch of one frame. centres, half_extents: (P, 3) box centres and half-extents (body units).
    """
    if pose.world_from_part.shape[0] != 1:
        raise ValueError(f"posed_box_bounds takes one frame, got {pose.world_from_part.shape[0]}")
    signs = torch.tensor(list(itertools.product((-1.0, 1.0), repeat=3)), dtype=centres.dtype, device=centres.device)
    local = (centres[:, None] + signs[None] * half_extents[:, None]) * pose.reach[0]  # (P, 8, 3)
    rotation, origin = pose.world_from_part[0, :, :3, :3], pose.world_from_part[0, :, :3, 3]
    corners = torch.einsum("pij,pkj->pki", rotation, local) + origin[:, None]
    flat = corners.reshape(-1, 3)
    return torch.stack([flat.amin(0), flat.amax(0)])


@torch.no_grad()
def query_points(
    field,
    points: torch.Tensor,
    pose: PoseBatch,
    dirs: torch.Tensor | None = None,
    samples_per_row: int = 64,
    chunk: int = 1 << 16,
    latent: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Evaluate a field at world points of one frame.

    Args:
        field: a Field. points: (N, 3) world points. pose: PoseBatch of one frame.
        dirs: optional (N, 3) unit viewing directions (colour depends on them); None evaluates density-first rows.
        samples_per_row: samples that share a row when ``dirs`` is None. chunk: points per forward pass.
        latent: optional (1, 2 L) autoencoder code.

    Returns:
        sigma (N,), rgb (N, 3), part_probs (N, P) or None when the field has no part selector.
    """
    check_shape("points", points, (-1, 3))
    if dirs is not None:
        check_shape("dirs", dirs, (points.shape[0], 3))
    per_row = 1 if dirs is not None else samples_per_row
    sigma, rgb, probs = [], [], []
    for start in range(0, points.shape[0], chunk):
        block = points[start : start + chunk]
        n = block.shape[0]
        rows = -(-n // per_row)
        padded = torch.cat([block, block[-1:].expand(rows * per_row - n, 3)]).reshape(rows, per_row, 3)
        if dirs is None:
            row_dirs = torch.zeros(rows, 3, dtype=points.dtype, device=points.device)
            row_dirs[:, 2] = 1
        else:
            row_dirs = dirs[start : start + chunk]
        frames = torch.zeros(rows, dtype=torch.long, device=points.device)
        out = field(padded, row_dirs, pose.select(frames), None if latent is None else latent.expand(rows, -1))
        sigma.append(out.sigma.reshape(-1)[:n])
        rgb.append(out.rgb.reshape(-1, 3)[:n])
        if out.part_probs is not None:
            probs.append(out.part_probs.reshape(rows * per_row, -1)[:n])
    return {
        "sigma": torch.cat(sigma),
        "rgb": torch.cat(rgb),
        "part_probs": torch.cat(probs) if probs else None,
    }


def nearest_part(field, points: torch.Tensor, pose: PoseBatch) -> torch.Tensor:
    """(N,) index of the part whose box holds each point most deeply (smallest max |u_i|), for fields without a
    part selector."""
    frames = torch.zeros(points.shape[0], dtype=torch.long, device=points.device)
    # the box coordinates the field's forward uses for its in-box test
    u = part_box_coordinates(points[:, None], pose.select(frames), field.box_centres, field.box_half_extents)
    return u.abs().amax(dim=-1)[:, 0].argmin(dim=-1)
