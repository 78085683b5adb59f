"""Stratified and importance sampling along rays (docs/model.md §5). Pure functions."""

from __future__ import annotations

import torch


def stratified_depths(
    near: torch.Tensor, far: torch.Tensor, n_samples: int, jitter: torch.Tensor | None = None
) -> torch.Tensor:
    """t_k = near + (k + U_k)/N (far - near).

    Args:
        near, far: (R,). n_samples: N. jitter: (R, N) uniform U_k in [0, 1); None uses 0.5 (deterministic).

    Returns:
        (R, N) increasing depths.
    """
    if jitter is None:
        jitter = torch.full((near.shape[0], n_samples), 0.5, dtype=near.dtype, device=near.device)
    steps = (torch.arange(n_samples, dtype=near.dtype, device=near.device) + jitter) / n_samples
    return near[:, None] + steps * (far - near)[:, None]


def importance_depths(
    bin_edges: torch.Tensor, weights: torch.Tensor, n_samples: int, uniform: torch.Tensor | None = None
) -> torch.Tensor:
    """Inverse-CDF samples from the piecewise-constant pdf proportional to max(w_k, 1e-8) over the bins.

    Args:
        bin_edges: (R, K + 1) increasing edges. weights: (R, K). n_samples: N.
        uniform: (R, N) in [0, 1); None uses evenly spaced quantiles (deterministic).

    Returns:
        (R, N) depths (unsorted when ``uniform`` is random).
    """
    pdf = weights.clamp_min(1e-8)
    pdf = pdf / pdf.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1)
    cdf[:, -1] = 1.0
    if uniform is None:
        uniform = (torch.arange(n_samples, dtype=weights.dtype, device=weights.device) + 0.5) / n_samples
        uniform = uniform.expand(weights.shape[0], n_samples).contiguous()
    index = torch.searchsorted(cdf, uniform.contiguous(), right=True).clamp(1, cdf.shape[-1] - 1)
    cdf_low, cdf_high = torch.gather(cdf, 1, index - 1), torch.gather(cdf, 1, index)
    edge_low, edge_high = torch.gather(bin_edges, 1, index - 1), torch.gather(bin_edges, 1, index)
    fraction = (uniform - cdf_low) / (cdf_high - cdf_low).clamp_min(1e-12)
    return edge_low + fraction * (edge_high - edge_low)
