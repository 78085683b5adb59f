"""Rendering rays as the fit renders its training rays (``fitting.trainer``): the ray bounds of the field's boxes
and occupancy grid, and the grid's proposal when the config asks for it."""

from __future__ import annotations

import torch

from fitting.config import FitConfig
from narf.fields.common import PoseBatch
from narf.occupancy import field_ray_bounds
from narf.renderer import bind_field, bind_grid_proposal, render_rays


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
