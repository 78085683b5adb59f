"""The fit's photometric loss over a batch of rays (docs/model.md §6): colour and mask terms."""

from __future__ import annotations

import torch

from fitting.config import FitConfig
from fitting.corrections import corrected_colour_error
from fitting.training_rays import render_training_rays


def ray_loss(
    config: FitConfig,
    field,
    batch,
    poses,
    generator,
    n_coarse: int,
    n_fine: int,
    latent=None,
    uniforms=None,
    normalisers: tuple[float, torch.Tensor] | None = None,
    randomized: bool = True,
    camera_colour=None,
    backgrounds: torch.Tensor | None = None,
):
    """L = mean 1/3 |C - C_gt|^2 + lambda_mask mean (M - M_gt)^2 (band skipped). Returns loss, colour MSE.

    ``latent``: optional (F, 2 * latent_dim) autoencoder codes, one per frame of ``poses``. ``uniforms``: the rays'
    sample draws (``render_rays``). ``normalisers``: (3 R, sum of mask weights) of the global batch when ``batch``
    is one process's share of it; both terms are then that share's contribution to the global means.
    ``randomized`` False: deterministic samples (``render_rays``), as full-image renders take them.
    ``camera_colour``: a ``fitting.corrections.CameraColour`` applied to the rendered colour of each ray's camera.
    ``backgrounds``: (R, 3) a background colour per ray, which also replaces the target outside the mask; the
    boundary band, whose target keeps the recording's own background, then leaves the colour loss as well
    (docs/model.md §6). Ray bounds and the grid proposal take the poses without gradient."""
    background = 1.0 if config.data.white_background else 0.0
    plain = camera_colour is None and backgrounds is None
    out = render_training_rays(
        config,
        field,
        batch.origins,
        batch.dirs,
        batch.frames,
        poses,
        n_coarse,
        n_fine,
        latent=latent,
        background=background if plain else 0.0,
        randomized=randomized,
        generator=generator,
        uniforms=uniforms,
    )
    colour_count, mask_count = normalisers or (out.rgb.numel(), batch.mask_weight.sum().clamp_min(1))
    if plain:
        colour = (out.rgb - batch.rgb).pow(2).sum() / colour_count
    else:
        colour = corrected_colour_error(out, batch, background, camera_colour, backgrounds, colour_count, mask_count)
    mask_term = (batch.mask_weight * (out.mask - batch.mask).pow(2)).sum() / mask_count
    return colour + config.train.mask_weight * mask_term, colour
