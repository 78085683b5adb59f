"""Image metrics (docs/model.md §7): PSNR, Mask L2. SSIM is scikit-image's (fitting.evaluate) to match the
reference evaluators exactly."""

from __future__ import annotations

import torch

MASK_L2_SCALE = 1e4  #: Mask L2 is reported x 10^4


def psnr(mse: torch.Tensor) -> torch.Tensor:
    """PSNR = 10 log10(1 / MSE) for RGB in [0, 1]."""
    return -10.0 * torch.log10(mse.clamp_min(1e-12))


def psnr_of(prediction: torch.Tensor, target: torch.Tensor, region: torch.Tensor | None = None) -> torch.Tensor:
    """PSNR over all pixels (H, W, 3) or over a boolean (H, W) region."""
    error = (prediction - target).pow(2).mean(dim=-1)
    return psnr(error[region].mean() if region is not None else error.mean())


def mask_l2(prediction: torch.Tensor, target: torch.Tensor, region: torch.Tensor | None = None) -> torch.Tensor:
    """mean (M - M_gt)^2 x 10^4 over all pixels or a region."""
    error = (prediction - target).pow(2)
    return MASK_L2_SCALE * (error[region].mean() if region is not None else error.mean())
