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


def point_encoding(
    values: torch.Tensor, gradient_freqs: int | None = None, without_pose: torch.Tensor | None = None
) -> torch.Tensor:
    """gamma_10(values), the point and box-coordinate encoding, whose gradient w.r.t. ``values`` passes through its
    ``gradient_freqs`` lowest frequencies only (None: all). The value is :func:`positional_encoding`'s, bit for bit,
    and so is every gradient that does not go through ``values``; only the pose correction's path, from the colour
    back to the part-local points and the pose, is band-limited. Its top frequencies (periods of about a millimetre over
    a box) make the loss over the pose rough at the scale of a tenth of a millimetre, so that their gradient says
    little about a turn of degrees (docs/model.md §6).

    Args:
        values: (..., D) part-local coordinates.
        gradient_freqs: frequencies k < gradient_freqs pass gradient; None or >= POINT_FREQS: all.
        without_pose: (..., D) the same values computed with the pose detached, where they also depend on trained
            weights (D-NARF's canonical point sum_i p_i x_i, whose selector p is trained): the higher frequencies
            then pass the weights' gradient through it and only the pose's is held. None: ``values.detach()``.

    Returns:
        (..., D * 2 POINT_FREQS), laid out as :func:`positional_encoding`'s.
    """
    if gradient_freqs is None or gradient_freqs >= POINT_FREQS or not values.requires_grad:
        return positional_encoding(values, POINT_FREQS)
    freqs = (2.0 ** torch.arange(POINT_FREQS, dtype=values.dtype, device=values.device)) * math.pi
    passing = torch.arange(POINT_FREQS, device=values.device) < gradient_freqs
    held = values.detach() if without_pose is None else without_pose
    angles = torch.where(passing, values[..., None] * freqs, held[..., None] * freqs)  # (..., D, L)
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1).flatten(-2)


def frequency_window(alpha: float, n_freqs: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """BARF's coarse-to-fine weights w_k(alpha) = (1 - cos(pi clamp(alpha - k, 0, 1))) / 2 of frequencies k < L: 1
    for k <= alpha - 1, 0 for k >= alpha, a half-cosine between. At an integer alpha the window keeps exactly the
    alpha lowest frequencies (docs/model.md §2).

    Returns:
        (2 L,) weights laid out as one scalar's :func:`positional_encoding` ([sin k, cos k]).
    """
    k = torch.arange(n_freqs, device=device, dtype=dtype)
    weights = (1 - torch.cos(math.pi * (alpha - k).clamp(0, 1))) / 2
    return torch.cat([weights, weights])


def windowed(encoded: torch.Tensor, alpha: float | None, n_freqs: int) -> torch.Tensor:
    """``encoded`` (..., D * 2L), a :func:`positional_encoding` of D scalars, times :func:`frequency_window`
    (alpha): unchanged (the same tensor) when alpha is None or >= L."""
    if alpha is None or alpha >= n_freqs:
        return encoded
    weights = frequency_window(alpha, n_freqs, encoded.device, encoded.dtype)
    return (encoded.unflatten(-1, (-1, 2 * n_freqs)) * weights).flatten(-2)
