"""The fit's photometric loss over a batch of rays (docs/model.md §6): colour and mask terms."""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import torch
from kornia.losses import charbonnier_loss

from fitting.config import FitConfig
from fitting.corrections import composited_colour, corrected_colour_error
from fitting.training_rays import render_training_rays
from narf.renderer import RenderOutput


def pseudo_huber(residual: torch.Tensor, delta: float) -> torch.Tensor:
    """rho(r) = 2 delta^2 (sqrt(1 + (r / delta)^2) - 1), elementwise (docs/model.md §6, *A robust colour loss*).

    r^2 to first order where |r| << delta, 2 delta |r| - 2 delta^2 where |r| >> delta: a pixel the field cannot
    match (a mask or body a few pixels off, a highlight) pulls on it with a bounded force, where r^2 pulls with 2 r.
    It is 2 delta^2 times kornia's Charbonnier loss of r / delta (Barron's general loss at alpha = 1, scale 1).
    ``delta`` 0: r^2 exactly. Any shape; returns the same shape."""
    if delta <= 0:
        return residual.square()
    scaled = residual / delta
    return 2 * delta**2 * charbonnier_loss(scaled, torch.zeros_like(scaled))


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
    """L = mean 1/3 sum_c rho(C_c - C_gt,c) + lambda_mask mean (M - M_gt)^2 (band skipped), rho the squared error or
    with ``train.colour_delta`` > 0 its pseudo-Huber (:func:`pseudo_huber`). Returns loss, colour MSE.

    ``latent``: optional (F, 2 * latent_dim) autoencoder codes, one per frame of ``poses``. ``uniforms``: the rays'
    sample draws (``render_rays``). ``normalisers``: (3 R, sum of mask weights) of the global batch when ``batch``
    is one process's share of it; both terms are then that share's contribution to the global means.
    ``randomized`` False: deterministic samples (``render_rays``), as full-image renders take them.
    ``camera_colour``: a ``fitting.corrections.CameraColour`` applied to the rendered colour of each ray's camera.
    ``backgrounds``: (R, 3) a background colour per ray, which also replaces the target outside the mask; the
    boundary band, whose target keeps the recording's own background, then leaves the colour loss as well
    (docs/model.md §6). Ray bounds and the grid proposal take the poses without gradient."""
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
        randomized=randomized,
        generator=generator,
        uniforms=uniforms,
    )
    return batch_loss(config, out, batch, normalisers, camera_colour, backgrounds)


def batch_loss(
    config: FitConfig,
    out: RenderOutput,
    batch,
    normalisers: tuple[float, torch.Tensor] | None = None,
    camera_colour=None,
    backgrounds: torch.Tensor | None = None,
):
    """:func:`ray_loss`'s loss and colour MSE from the rays' render ``out`` over a black background (what
    ``fitting.training_rays`` renders): the data's background is composited here, C + (1 - M) bg, where
    ``camera_colour`` and ``backgrounds`` are None, and by ``corrected_colour_error`` otherwise."""
    background = 1.0 if config.data.white_background else 0.0
    plain = camera_colour is None and backgrounds is None
    if plain and background:
        out = replace(out, rgb=out.rgb + (1 - out.mask)[:, None] * background)
    colour_count, mask_count = normalisers or (out.rgb.numel(), batch.mask_weight.sum().clamp_min(1))

    def colour_error(penalty) -> torch.Tensor:
        if plain:
            return penalty(out.rgb - batch.rgb).sum() / colour_count
        terms = (out, batch, background, camera_colour, backgrounds, colour_count, mask_count)
        return corrected_colour_error(*terms, penalty=penalty)

    delta = config.train.colour_delta
    colour = colour_error(torch.square)
    robust = colour_error(partial(pseudo_huber, delta=delta)) if delta > 0 else colour
    mask_term = (batch.mask_weight * (out.mask - batch.mask).pow(2)).sum() / mask_count
    return robust + config.train.mask_weight * mask_term, colour


def ray_colour_errors(config: FitConfig, out: RenderOutput, batch, camera_colour=None) -> torch.Tensor:
    """(R,) each ray's squared colour error, the mean over its channels: C = T_c(sum w c) + (1 - M) bg against the
    target, ``out`` rendered over black as :func:`ray_loss` renders it, ``camera_colour`` (T_c) applied as it applies
    it. Their mean is :func:`ray_loss`'s colour MSE without random backgrounds."""
    background = 1.0 if config.data.white_background else 0.0
    return (composited_colour(out, batch, background, camera_colour) - batch.rgb).square().mean(dim=-1)
