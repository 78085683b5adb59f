"""Rendering rays as the fit renders its training rays (``fitting.trainer``): the ray bounds of the field's boxes
and occupancy grid, and the grid's proposal when the config asks for it; and a step's several sets of rays (the
training rays, the virtual rays of ``fitting.unseen``) in one render."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from fitting.config import FitConfig
from narf.fields.common import PoseBatch, cat_poses
from narf.occupancy import field_ray_bounds
from narf.renderer import RenderOutput, bind_field, bind_grid_proposal, render_rays


def render_training_rays(
    config: FitConfig,
    field,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    frames: torch.Tensor,
    poses: PoseBatch,
    n_coarse: int,
    n_fine: int,
    **options,
):
    """Render rays (R,) of ``frames`` (indices into ``poses``) as the fit does: bounds from the field's boxes (and
    grid), the occupancy grid's proposal for randomized training renders when the config asks for it (validate_config
    ties it to render.occupancy, so the field has its grid), both with the poses without gradient. ``options``:
    ``latent`` for :func:`narf.renderer.bind_field`, the rest for :func:`narf.renderer.render_rays`."""
    latent = options.pop("latent", None)
    near, far, hit = field_ray_bounds(field, origins, dirs, poses.select(frames).detach())
    proposal = None
    if config.render.grid_proposal and options.get("randomized", True):
        proposal = bind_grid_proposal(field, poses.detach(), frames)
    field_fn = bind_field(field, dirs, poses, frames, latent)
    return render_rays(field_fn, origins, dirs, near, far, hit, n_coarse, n_fine, proposal_fn=proposal, **options)


@dataclass
class RaySet:
    """Rays to render in a training step: origins and unit dirs (R, 3), frames (R,) long indices into ``poses``, and
    their sample draws ``uniforms`` ((R, n_coarse), (R, n_fine)) in [0, 1)."""

    origins: torch.Tensor
    dirs: torch.Tensor
    frames: torch.Tensor
    poses: PoseBatch
    uniforms: list[torch.Tensor]


def render_ray_sets(config: FitConfig, field, sets: list[RaySet], n_coarse: int, n_fine: int) -> list[RenderOutput]:
    """Render several ray sets, each with its own poses, in one :func:`render_training_rays` call (background 0):
    their poses concatenated (:func:`narf.fields.common.cat_poses`, each PoseBatch object once), their frames
    offset to match, and the output split back per set. A ray's samples and field values depend only on its own
    frame and draws, so each set's output equals rendering it alone up to rounding (the field's matrix products see
    larger batches); one call runs the field's per-part loops, the ray bounds and the grid proposal once for all the
    sets instead of once per set (docs/results/benchmark.md, *The step's renders in one call*).

    Returns:
        one RenderOutput per set, in order; ``sample_weights`` and ``hit_ids`` of each set's own hit rays.
    """
    pose_batches, offset_of, offsets = [], {}, []
    for s in sets:
        if id(s.poses) not in offset_of:
            offset_of[id(s.poses)] = sum(len(p.reach) for p in pose_batches)
            pose_batches.append(s.poses)
        offsets.append(offset_of[id(s.poses)])
    poses = pose_batches[0] if len(pose_batches) == 1 else cat_poses(pose_batches)
    frames = torch.cat([s.frames + offset for s, offset in zip(sets, offsets)])
    origins, dirs = torch.cat([s.origins for s in sets]), torch.cat([s.dirs for s in sets])
    uniforms = [torch.cat([s.uniforms[k] for s in sets]) for k in range(2)]
    out = render_training_rays(config, field, origins, dirs, frames, poses, n_coarse, n_fine, uniforms=uniforms)
    return split_output(out, [len(s.frames) for s in sets])


def render_each_set(config: FitConfig, field, sets: list[RaySet], n_coarse: int, n_fine: int) -> list[RenderOutput]:
    """:func:`render_ray_sets`' reference: each set rendered by a call of its own (as the fit rendered them before);
    the same outputs up to rounding."""
    return [render_ray_sets(config, field, [s], n_coarse, n_fine)[0] for s in sets]


def split_output(out: RenderOutput, counts: list[int]) -> list[RenderOutput]:
    """A RenderOutput of consecutive ray sets of ``counts`` rays each, as one RenderOutput per set."""
    parts, start = [], 0
    for count in counts:
        end = start + count
        sample_weights = hit_ids = None
        if out.hit_ids is not None:
            mine = (out.hit_ids >= start) & (out.hit_ids < end)
            if mine.any():
                sample_weights, hit_ids = out.sample_weights[mine], out.hit_ids[mine] - start
        part_weights = None if out.part_weights is None else out.part_weights[start:end]
        parts.append(
            RenderOutput(
                out.rgb[start:end], out.mask[start:end], out.depth[start:end], part_weights, sample_weights, hit_ids
            )
        )
        start = end
    return parts
