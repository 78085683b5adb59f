"""Views nobody trained on (docs/model.md §6, *Unseen views*; not in the paper): rays from random virtual cameras
around each training frame's body, InfoNeRF's ray entropy (Kim et al., CVPR 2022) over them, and RegNeRF's depth
smoothness (Niemeyer et al., CVPR 2022) over small patches of them, and the colour's left-right symmetry: each
virtual ray and its mirror image, rendered in the mirror-image pose, should see the same colour.

With few training cameras, density that lies inside every training mask but outside the person is not seen by the
loss, and shows from a new camera as a wrong silhouette or a halo. The entropy term asks each virtual ray that meets
some density to concentrate it: a ray through a thin halo (weights spread along it) costs more than one that hits a
surface (one weight near its opacity). The smoothness term asks neighbouring pixels of a virtual patch to see the
surface at nearly the same depth: floaters and ridges that no training camera saw make depth jump."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import nn

from fitting.config import FitConfig
from fitting.data import OutlineRays
from fitting.training_rays import RaySet, render_each_set
from narf.fields.common import PoseBatch
from narf.renderer import RenderOutput

#: virtual cameras stand this many reaches s from the pelvis (about 2.2 m for an adult's 1.1 m), and aim at points
#: within this many reaches of it along each axis
VIRTUAL_DISTANCE = 2.0
VIRTUAL_SPREAD = 0.6
#: RegNeRF's patches: PATCH_SIDE^2 pixels, PATCH_PITCH reaches apart where the patch's centre ray meets its aim point
#: (1.1 cm for an adult: about a pixel of the training images at the CPU preset's resolution)
PATCH_SIDE = 8
PATCH_PITCH = 0.01
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
    origins, target, frame = _virtual_cameras(poses, frames, n_rays, generator)
    dirs = target - origins
    return origins, dirs / dirs.norm(dim=-1, keepdim=True), frame


def _virtual_cameras(poses: PoseBatch, frames: torch.Tensor, n: int, generator: torch.Generator):
    """n virtual cameras as :func:`virtual_rays` draws them: origins (n, 3), aim points (n, 3), frames (n,)."""
    device = poses.world_from_part.device
    pick = torch.randint(0, frames.numel(), (n,), generator=generator).to(device)
    frame = frames[pick]
    pelvis, reach = poses.world_from_part[frame, 0, :3, 3], poses.reach[frame, None]
    away = torch.randn(n, 3, generator=generator).to(device)
    away = away / away.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    target = pelvis + reach * VIRTUAL_SPREAD * (2 * torch.rand(n, 3, generator=generator).to(device) - 1)
    return pelvis + reach * VIRTUAL_DISTANCE * away, target, frame


def virtual_patches(
    poses: PoseBatch, frames: torch.Tensor, n_patches: int, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Square patches of PATCH_SIDE^2 rays from virtual cameras drawn as :func:`virtual_rays`' (RegNeRF's patches):
    patch n's rays leave its camera o_n towards t_n + s (i - (S-1)/2) PATCH_PITCH r_n + s (j - (S-1)/2)
    PATCH_PITCH u_n, with r_n, u_n unit vectors square to the centre ray and to each other (rolled at random).

    Args:
        poses, frames, generator: as :func:`virtual_rays`. n_patches: N.

    Returns:
        origins (N*S*S, 3), unit dirs (N*S*S, 3) and frames (N*S*S,), patch by patch, row-major within a patch.
    """
    origins, target, frame = _virtual_cameras(poses, frames, n_patches, generator)
    forward = nn.functional.normalize(target - origins, dim=-1)
    roll = torch.randn(n_patches, 3, generator=generator).to(origins.device)
    right = nn.functional.normalize(torch.linalg.cross(forward, roll), dim=-1)
    up = torch.linalg.cross(right, forward)
    steps = (torch.arange(PATCH_SIDE, dtype=origins.dtype, device=origins.device) - (PATCH_SIDE - 1) / 2) * PATCH_PITCH
    rows, cols = torch.meshgrid(steps, steps, indexing="ij")  # (S, S)
    scale = poses.reach[frame][:, None, None, None]
    aims = target[:, None, None] + scale * (
        rows[..., None] * up[:, None, None] + cols[..., None] * right[:, None, None]
    )
    dirs = nn.functional.normalize(aims - origins[:, None, None], dim=-1).reshape(-1, 3)
    per_ray = PATCH_SIDE * PATCH_SIDE
    return origins.repeat_interleave(per_ray, dim=0), dirs, frame.repeat_interleave(per_ray)


def depth_smoothness(depth: torch.Tensor, opacity: torch.Tensor, reach: torch.Tensor) -> torch.Tensor:
    """RegNeRF's depth smoothness over patches: the mean over neighbouring pixel pairs (a, b) of
    ((d_a - d_b) / s)^2, each pair weighed by M_a M_b, with d = D / M the depth where the ray's opacity M is and s
    the frame's reach (so the term does not depend on the body's units). Pairs across the silhouette weigh little,
    and the weights carry no gradient: the term moves depth, not the silhouette.

    Args:
        depth: (N, S, S) unnormalised depths D = sum w t (``RenderOutput.depth``). opacity: (N, S, S) M = sum w.
        reach: (N,) of each patch's frame.

    Returns:
        () the weighted mean (0 where no pair has opacity), differentiable in the depths and opacities.
    """
    d = depth / opacity.clamp_min(1e-6) / reach[:, None, None]
    total, weight = depth.sum() * 0, depth.sum() * 0
    for a, b, ma, mb in (
        (d[:, 1:], d[:, :-1], opacity[:, 1:], opacity[:, :-1]),
        (d[:, :, 1:], d[:, :, :-1], opacity[:, :, 1:], opacity[:, :, :-1]),
    ):
        pair = (ma * mb).detach()
        total, weight = total + (pair * (a - b).pow(2)).sum(), weight + pair.sum()
    return total / weight.clamp_min(1e-6)


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


@dataclass
class VirtualTerm:
    """A loss term on virtual rays: the ray sets it renders and its weighted value from their outputs (in order)."""

    sets: list[RaySet]
    value: Callable[[list[RenderOutput]], torch.Tensor]


def unseen_terms(config: FitConfig, poses: PoseBatch, frames: torch.Tensor, generator: torch.Generator):
    """The fit's terms on views nobody trained on, drawn from ``generator`` in this order: ``train.entropy_weight``
    times the ray entropy over ``train.virtual_rays`` virtual rays, then ``train.smoothness_weight`` times the depth
    smoothness over ``train.virtual_patches`` virtual patches, around the bodies of ``frames`` (a step's frame
    indices into ``poses``). Only the terms of weight > 0 (none: nothing drawn). Returns a list of VirtualTerm."""
    t, terms = config.train, []
    drawn = torch.unique(frames)
    if t.entropy_weight > 0:
        origins, dirs, frame = virtual_rays(poses, drawn, t.virtual_rays, generator)
        ray_set = virtual_set(config, origins, dirs, frame, poses, generator)
        terms.append(VirtualTerm([ray_set], lambda out: t.entropy_weight * ray_entropy(out[0].sample_weights)))
    if t.smoothness_weight > 0:
        origins, dirs, frame = virtual_patches(poses, drawn, t.virtual_patches, generator)
        shape, reach = (-1, PATCH_SIDE, PATCH_SIDE), poses.reach[frame[:: PATCH_SIDE * PATCH_SIDE]]

        def smoothness(out: list[RenderOutput]) -> torch.Tensor:
            depth, opacity = out[0].depth.reshape(shape), out[0].mask.reshape(shape)
            return t.smoothness_weight * depth_smoothness(depth, opacity, reach)

        terms.append(VirtualTerm([virtual_set(config, origins, dirs, frame, poses, generator)], smoothness))
    return terms


def unseen_views_loss(config: FitConfig, field, poses: PoseBatch, frames: torch.Tensor, generator: torch.Generator):
    """The :func:`unseen_terms`' sum, each set rendered alone (the reference the trainer's one render of every set
    is tested against). 0 when both weights are 0 (nothing drawn, nothing rendered)."""
    return terms_rendered_alone(config, field, unseen_terms(config, poses, frames, generator))


def terms_rendered_alone(config: FitConfig, field, terms: list[VirtualTerm]) -> torch.Tensor | float:
    """The sum of the terms' values, each of their ray sets rendered by a call of its own (0.0 for no terms)."""
    r, sets = config.render, [s for term in terms for s in term.sets]
    return terms_value(terms, render_each_set(config, field, sets, r.train_coarse, r.train_fine))


def terms_value(terms: list[VirtualTerm], outputs: list[RenderOutput]) -> torch.Tensor | float:
    """The sum of the terms' values from the outputs of their sets, in order (0.0 for no terms)."""
    total, first = 0.0, 0
    for term in terms:
        total, first = total + term.value(outputs[first : first + len(term.sets)]), first + len(term.sets)
    return total


def virtual_set(config: FitConfig, origins, dirs, frame, poses: PoseBatch, generator: torch.Generator) -> RaySet:
    """Virtual rays as a RaySet, their stratified draws from the fit's CPU generator (moved: a CPU generator cannot
    draw on a GPU), rendered as the training rays are."""
    r, device = config.render, origins.device
    uniforms = [torch.rand(len(frame), k, generator=generator).to(device) for k in (r.train_coarse, r.train_fine)]
    return RaySet(origins, dirs, frame, poses, uniforms)


def sagittal_reflections(poses: PoseBatch) -> torch.Tensor:
    """Each frame's reflection about its sagittal plane, S = I - 2 n n^T with n the root part's x axis: (B, 3, 3)."""
    normal = poses.world_from_part[:, 0, :3, 0]
    eye = torch.eye(3, dtype=normal.dtype, device=normal.device)
    return eye - 2 * normal[:, :, None] * normal[:, None, :]


def mirror_rays(
    origins: torch.Tensor, dirs: torch.Tensor, frame: torch.Tensor, poses: PoseBatch
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays reflected about their frame's sagittal plane: the plane through the pelvis (the root part's origin)
    normal to the root's x axis, x' = c + S (x - c), d' = S d with S = I - 2 n n^T.

    Args:
        origins, dirs: (R, 3). frame: (R,) indices into ``poses``.

    Returns:
        the reflected origins and directions, (R, 3) each.
    """
    root = poses.world_from_part[frame, 0]
    normal, centre = root[:, :3, 0], root[:, :3, 3]

    def reflect(v: torch.Tensor) -> torch.Tensor:
        return v - 2 * (v * normal).sum(-1, keepdim=True) * normal

    return centre + reflect(origins - centre), reflect(dirs)


def mirror_terms(
    config: FitConfig, poses: PoseBatch, mirrored: PoseBatch | None, frames: torch.Tensor, generator: torch.Generator
) -> list[VirtualTerm]:
    """``train.mirror_weight`` times the colour's left-right asymmetry (docs/model.md §6, *Left-right symmetry*):
    over ``train.mirror_rays`` virtual rays around the bodies of ``frames`` (as :func:`virtual_rays`), each rendered
    in its frame's pose and, reflected (:func:`mirror_rays`), in the mirror-image pose ``mirrored``, the mean of
    |c - c'|^2 / 3 over the colours c = C / M of the pairs (:func:`symmetry_error`), weighed by M M' where both
    opacities exceed 0.5 (rays beside the body, or through an outline the mirror does not repeat, weigh nothing; the
    weights carry no gradient). No term when the weight is 0 or there are no mirror-image poses (nothing drawn).
    Returns a list of at most one VirtualTerm, whose two sets are the rays and their mirror images."""
    weight = config.train.mirror_weight
    if weight <= 0 or mirrored is None:
        return []
    origins, dirs, frame = virtual_rays(poses, torch.unique(frames), config.train.mirror_rays, generator)
    seen = virtual_set(config, origins, dirs, frame, poses, generator)
    # a shading field sees the mirror image under the mirror image of the light (docs/model.md §3, *Shading*)
    mirrored = replace(mirrored, light_from_world=sagittal_reflections(poses))
    mirror = virtual_set(config, *mirror_rays(origins, dirs, frame, poses), frame, mirrored, generator)

    def asymmetry(out: list[RenderOutput]) -> torch.Tensor:
        return weight * symmetry_error(out[0].rgb, out[0].mask, out[1].rgb, out[1].mask)

    return [VirtualTerm([seen, mirror], asymmetry)]


def mirror_colour_loss(
    config: FitConfig,
    field,
    poses: PoseBatch,
    mirrored: PoseBatch | None,
    frames: torch.Tensor,
    generator: torch.Generator,
) -> torch.Tensor | float:
    """The :func:`mirror_terms`' value, each set rendered alone (the reference the trainer's one render of every set
    is tested against); 0 when the weight is 0."""
    return terms_rendered_alone(config, field, mirror_terms(config, poses, mirrored, frames, generator))


def outline_terms(
    config: FitConfig, outlines: OutlineRays | None, poses: PoseBatch, generator: torch.Generator
) -> list[VirtualTerm]:
    """``train.outline_weight`` times the outline error (docs/model.md §6, *The bodies' outline from unseen views*)
    over ``train.outline_rays`` rays drawn uniformly from ``outlines`` (from those that meet the body alone where
    ``train.outline_beside`` is 0), each rendered in its training frame's pose (``poses``, indexed by training
    frame). No term when the weight is 0 or there are no outline rays (nothing drawn). Returns a list of at most one
    VirtualTerm."""
    t = config.train
    if t.outline_weight <= 0 or outlines is None:
        return []
    if t.outline_beside > 0:
        pick = torch.randint(0, len(outlines.inside), (t.outline_rays,), generator=generator)
    else:  # the rays through the body alone
        pick = torch.multinomial(outlines.inside.cpu(), t.outline_rays, replacement=True, generator=generator)
    pick = pick.to(outlines.inside.device)
    rays = virtual_set(config, outlines.origins[pick], outlines.dirs[pick], outlines.frames[pick], poses, generator)
    inside = outlines.inside[pick]
    weights = inside + t.outline_beside * (1 - inside)

    def outline(out: list[RenderOutput]) -> torch.Tensor:
        return t.outline_weight * outline_error(out[0].mask, inside, weights)

    return [VirtualTerm([rays], outline)]


def outline_error(opacity: torch.Tensor, inside: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """sum_r w_r (M_r - B_r)^2 / sum_r w_r: the rays' opacities M (R,) against B (R,), 1 where the ray meets the body
    and 0 where it passes beside it, weighed by w (R,) (None: all 1); the mask term's form
    (``fitting.losses.batch_loss``) on rays no camera recorded."""
    if weights is None:
        return (opacity - inside).square().mean()
    return (weights * (opacity - inside).square()).sum() / weights.sum().clamp_min(1e-6)


def symmetry_error(rgb: torch.Tensor, mask: torch.Tensor, rgb_mirror: torch.Tensor, mask_mirror: torch.Tensor):
    """sum_r w_r |C_r / M_r - C'_r / M'_r|^2 / (3 max(sum_r w_r, 1)), w_r = M_r M'_r [M_r > 0.5][M'_r > 0.5] (no
    gradient): rgb (R, 3) and mask (R,) of the rays, the same of their mirror images; 0 where no pair is opaque, and
    a step with under one pair's weight counts less."""
    both = (mask * mask_mirror * ((mask > 0.5) & (mask_mirror > 0.5))).detach()
    colour = rgb / mask.clamp_min(1e-4)[:, None]
    colour_mirror = rgb_mirror / mask_mirror.clamp_min(1e-4)[:, None]
    return (both * (colour - colour_mirror).pow(2).sum(-1)).sum() / (3 * both.sum().clamp_min(1.0))
