"""The fit's photometric loss over a batch of rays (docs/model.md §6): colour and mask terms."""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import torch
from kornia.filters import get_gaussian_kernel1d
from kornia.losses import charbonnier_loss

from fitting.config import FitConfig
from fitting.corrections import background_target, composited_colour, corrected_colour_error
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


#: S3IM's group: SIDE x SIDE rays under SSIM's Gaussian window (sigma 1.5), as a 4 x 4 kernel of stride 4 takes them
SIDE = 4
#: SSIM's stabilisers for values in [0, 1]: (0.01)^2 and (0.03)^2 (Wang et al., 2004)
SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2


def grouped_ssim(x: torch.Tensor, y: torch.Tensor, side: int = SIDE) -> torch.Tensor:
    """SSIM of each group of ``side``^2 consecutive rays, per channel, under a separable Gaussian window (sigma 1.5)
    laid on the group as a side x side patch, row-major:

    SSIM = (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_x^2 + s_y^2 + C2)), mu, s^2 and s_xy the
    window's weighted means, variances and covariance. x, y: (G * side^2, C) values in [0, 1]. Returns (G, C).
    On one side x side patch it is SSIM's value over a window of the patch's size (kornia's ``metrics.ssim`` with
    ``padding="valid"``)."""
    if x.shape != y.shape or x.shape[0] % side**2:
        raise ValueError(
            f"grouped_ssim: shapes {tuple(x.shape)} / {tuple(y.shape)}, rows not whole groups of {side**2}"
        )
    line = get_gaussian_kernel1d(side, 1.5, force_even=True, device=x.device, dtype=x.dtype)[0]
    window = (line[:, None] * line[None, :]).reshape(1, side**2, 1)
    gx, gy = x.reshape(-1, side**2, x.shape[-1]), y.reshape(-1, side**2, y.shape[-1])
    mean_x, mean_y = (window * gx).sum(1), (window * gy).sum(1)
    var_x = (window * gx.square()).sum(1) - mean_x.square()
    var_y = (window * gy.square()).sum(1) - mean_y.square()
    cov = (window * gx * gy).sum(1) - mean_x * mean_y
    numerator = (2 * mean_x * mean_y + SSIM_C1) * (2 * cov + SSIM_C2)
    return numerator / ((mean_x.square() + mean_y.square() + SSIM_C1) * (var_x + var_y + SSIM_C2))


def stochastic_ssim_loss(
    rendered: torch.Tensor,
    target: torch.Tensor,
    repeats: int,
    generator: torch.Generator,
    labels: torch.Tensor | None = None,
) -> torch.Tensor:
    """S3IM (Xie et al., ICCV 2023): 1 - the mean :func:`grouped_ssim` over ``repeats`` random orderings of the
    rays, each cut into groups of SIDE^2 (the rays past the last whole group of an ordering are left out of it).
    A ray's colour is then judged with others' from anywhere in the batch: their means, contrasts and correlation,
    which a per-ray loss does not see. With ``labels`` (R,) ints, a group takes rays of one label only (an ordering
    is random within each label, and each label's rays past its last whole group are left out). rendered, target:
    (R, 3). Returns a 0-dim tensor."""
    count = rendered.shape[0]
    labels = torch.zeros(count, dtype=torch.long) if labels is None else labels.cpu()  # one label: the whole batch
    orders = [_grouped_order(labels, generator) for _ in range(repeats)]
    order = torch.cat(orders).to(rendered.device)
    if order.numel() == 0:
        return rendered.sum() * 0
    return 1 - grouped_ssim(rendered[order], target[order]).mean()


def _grouped_order(labels: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """A random order of the rays cut to whole groups of SIDE^2, each group of one label (``labels`` (R,) ints on the
    CPU): a random permutation, sorted stably by label, then the rays past each label's last whole group dropped.
    (N,) indices, N a multiple of SIDE^2."""
    order = torch.randperm(labels.shape[0], generator=generator)
    sorted_label, by_label = torch.sort(labels[order], stable=True)
    order = order[by_label]
    _, sizes = torch.unique_consecutive(sorted_label, return_counts=True)
    starts = torch.repeat_interleave(torch.cumsum(sizes, 0) - sizes, sizes)
    whole = torch.repeat_interleave(sizes // SIDE**2 * SIDE**2, sizes)
    return order[torch.arange(labels.shape[0]) - starts < whole]


def structure_term(config: FitConfig, out: RenderOutput, batch, generator, camera_colour=None, backgrounds=None):
    """``train.s3im_weight`` times :func:`stochastic_ssim_loss` of the rays' colours composited as :func:`batch_loss`
    composites them, against their targets (docs/model.md §6, *Structure across rays*). With random ``backgrounds``
    (R, 3) the rays are composited over them, the targets outside the mask are those colours, and the band's rays
    (mask weight 0) leave the groups as they leave the colour term. With ``train.s3im_groups`` "camera", a group takes
    the rays of one training camera only. A 0-dim tensor."""
    if backgrounds is None:
        background = 1.0 if config.data.white_background else 0.0
        rendered, target, cameras = composited_colour(out, batch, background, camera_colour), batch.rgb, batch.cameras
    else:
        kept = batch.mask_weight > 0
        rendered = composited_colour(out, batch, backgrounds, camera_colour)[kept]
        target, cameras = background_target(batch, backgrounds)[kept], batch.cameras[kept]
    labels = cameras if config.train.s3im_groups == "camera" else None
    loss = stochastic_ssim_loss(rendered, target, config.train.s3im_repeats, generator, labels)
    return config.train.s3im_weight * loss
