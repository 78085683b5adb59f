"""Views nobody trained on (docs/model.md §6, *Unseen views*; not in the paper): rays from random virtual cameras
around each training frame's body, and InfoNeRF's ray entropy (Kim et al., CVPR 2022) over them.

With few training cameras, density that lies inside every training mask but outside the person is not seen by the
loss, and shows from a new camera as a wrong silhouette or a halo. The entropy term asks each virtual ray that meets
some density to concentrate it: a ray through a thin halo (weights spread along it) costs more than one that hits a
surface (one weight near its opacity)."""

from __future__ import annotations

import torch

from narf.fields.common import PoseBatch

#: virtual cameras stand this many reaches s from the pelvis (about 2.2 m for an adult's 1.1 m), and aim at points
#: within this many reaches of it along each axis
VIRTUAL_DISTANCE = 2.0
VIRTUAL_SPREAD = 0.6
#: InfoNeRF's threshold: rays whose opacity is below it (they pass beside the body) are left out
ENTROPY_MIN_OPACITY = 0.1


def virtual_rays(
    poses: PoseBatch, frames: torch.Tensor, n_rays: int, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays of random virtual cameras around the bodies of ``frames``: each ray takes one of them at random, starts
    ``VIRTUAL_DISTANCE`` s from its pelvis along a uniformly random direction and aims at a uniform point of the
    cube of half-side ``VIRTUAL_SPREAD`` s about the pelvis.

    Args:
        poses: the PoseBatch the frame indices point into. frames: (F,) long, the frames to draw from.
        n_rays: R. generator: the CPU generator the draws come from (the fit's own, so a resumed fit repeats them).

    Returns:
        origins (R, 3), unit dirs (R, 3) and frame (R,) indices into ``poses``, on ``poses``' device.
    """
    device = poses.world_from_part.device
    pick = torch.randint(0, frames.numel(), (n_rays,), generator=generator).to(device)
    frame = frames[pick]
    pelvis, reach = poses.world_from_part[frame, 0, :3, 3], poses.reach[frame, None]
    away = torch.randn(n_rays, 3, generator=generator).to(device)
    away = away / away.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    target = pelvis + reach * VIRTUAL_SPREAD * (2 * torch.rand(n_rays, 3, generator=generator).to(device) - 1)
    origins = pelvis + reach * VIRTUAL_DISTANCE * away
    dirs = target - origins
    return origins, dirs / dirs.norm(dim=-1, keepdim=True), frame


def ray_entropy(sample_weights: torch.Tensor | None, min_opacity: float = ENTROPY_MIN_OPACITY) -> torch.Tensor:
    """InfoNeRF's ray entropy: the mean over rays of opacity >= ``min_opacity`` of H = -sum_k p_k log p_k with
    p_k = w_k / sum_j w_j, the ray's compositing weights normalised (0 for a ray whose density is one sample, up to
    log K for density spread evenly over its K samples). The paper normalises alpha_k; the weights w_k are the
    share of the ray's colour each sample gives, which is what a halo spreads.

    Args:
        sample_weights: (R', K) weights of the rays that hit a box (``RenderOutput.sample_weights``), or None.

    Returns:
        () the mean entropy (0 when no ray qualifies), differentiable in the weights.
    """
    if sample_weights is None or sample_weights.numel() == 0:
        return torch.zeros(())
    opacity = sample_weights.sum(dim=-1)
    kept = opacity >= min_opacity
    if not kept.any():
        return sample_weights.sum() * 0
    p = sample_weights[kept] / opacity[kept, None]
    return -(p * torch.log(p.clamp_min(1e-10))).sum(dim=-1).mean()
