"""Positional encoding gamma_L (docs/model.md §2)."""

from __future__ import annotations

import math

import torch


def positional_encoding(values: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """gamma_L(v) = (sin(2^k pi v), cos(2^k pi v)) for k < L, per scalar, no identity term.

    Args:
        values: (..., D) inputs (period 2: use values in [-1, 1] to avoid aliasing).
        n_freqs: L.

    Returns:
        (..., D * 2L), laid out per scalar as [sin k=0..L-1, cos k=0..L-1].
    """
    freqs = (2.0 ** torch.arange(n_freqs, dtype=values.dtype, device=values.device)) * math.pi
    angles = values[..., None] * freqs  # (..., D, L)
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1).flatten(-2)


def encoding_dim(n_inputs: int, n_freqs: int) -> int:
    """Output width of ``positional_encoding`` for ``n_inputs`` scalars."""
    return 2 * n_inputs * n_freqs


#: Frequencies L of each encoded input (docs/model.md §2): gamma_10 for points and box coordinates, gamma_4 for
#: the bone lengths zeta, the pose features xi and directions.
POINT_FREQS = 10
POSE_FREQS = 4
#: Encoded widths: a 3D point or box coordinate (60), a direction (24), one part's xi, 6 values (48).
POINT_WIDTH = encoding_dim(3, POINT_FREQS)
DIRECTION_WIDTH = encoding_dim(3, POSE_FREQS)
XI_WIDTH = encoding_dim(6, POSE_FREQS)


def zeta_width(n_parts: int) -> int:
    """Width of gamma_4(zeta), one bone length per part: 152 for NARF's 19 parts."""
    return encoding_dim(n_parts, POSE_FREQS)
