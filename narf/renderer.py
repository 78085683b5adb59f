"""Volume rendering shared by every NeRF-type model (docs/model.md §5). The field is passed as a callable.

``field_fn(points (R', S, 3), ray_ids (R',)) -> FieldOutput`` evaluates the samples of the rays ``ray_ids``
(indices into the ray batch), so the caller binds directions, poses and latents (see :func:`bind_field`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from narf.extraction import posed_box_bounds
from narf.fields.base import FieldOutput
from narf.fields.common import part_box_coordinates
from narf.geometry import check_shape
from narf.occupancy import field_ray_bounds, grid_density
from narf.rays import image_pixels, ray_box_intersect, rays_from_pixels
from narf.sampling import importance_depths, stratified_depths


@dataclass
class RenderOutput:
    """rgb (R, 3); mask (R,) accumulated alpha; depth (R,) expected depth; part_weights (R, P) = sum_k w_k p_k
    (None when the field has no parts); sample_weights (R', K) the compositing weights w_k of the rays that hit a
    box, whose indices are ``hit_ids`` (R',) (None when no ray hit)."""

    rgb: torch.Tensor
    mask: torch.Tensor
    depth: torch.Tensor
    part_weights: torch.Tensor | None = None
    sample_weights: torch.Tensor | None = None
    hit_ids: torch.Tensor | None = None

    def segmentation(self) -> torch.Tensor:
        """(R,) argmax part where mask >= 0.5, else -1."""
        if self.part_weights is None:
            raise ValueError("this model has no part probabilities: no segmentation")
        labels = self.part_weights.argmax(dim=-1)
        return torch.where(self.mask >= 0.5, labels, torch.full_like(labels, -1))


def weights_from_density(sigmas: torch.Tensor, depths: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """w_k = alpha_k prod_{j<k} (1 - alpha_j), alpha_k = 1 - exp(-sigma_k delta_k), delta_k = t_{k+1} - t_k with
    t_{K+1} = far.

    Args:
        sigmas, depths: (R, K). far: (R,).

    Returns:
        (R, K) weights.
    """
    deltas = torch.diff(torch.cat([depths, far[:, None]], dim=-1), dim=-1).clamp_min(0)
    alphas = 1 - torch.exp(-sigmas * deltas)
    transmittance = torch.cumprod(torch.cat([torch.ones_like(alphas[:, :1]), 1 - alphas + 1e-10], dim=-1), dim=-1)
    return alphas * transmittance[:, :-1]


def composite(weights: torch.Tensor, colours: torch.Tensor, depths: torch.Tensor, background: float | torch.Tensor):
    """C = sum w c + (1 - M) bg, M = sum w, D = sum w t. Returns rgb (R, 3), mask (R,), depth (R,)."""
    mask = weights.sum(dim=-1)
    rgb = (weights[..., None] * colours).sum(dim=-2) + (1 - mask)[:, None] * background
    return rgb, mask, (weights * depths).sum(dim=-1)


def render_rays(
    field_fn: Callable,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    near: torch.Tensor,
    far: torch.Tensor,
    hit: torch.Tensor,
    n_coarse: int,
    n_fine: int,
    background: float = 0.0,
    randomized: bool = True,
    generator: torch.Generator | None = None,
    uniforms: tuple[torch.Tensor, torch.Tensor] | None = None,
    proposal_fn: Callable | None = None,
) -> RenderOutput:
    """Coarse pass without gradient, importance samples, then one final pass over all sorted samples with
    gradient through the same network. Rays that miss every box are not evaluated (C = bg, M = 0).

    Args:
        field_fn: see module docstring. origins, dirs: (R, 3). near, far: (R,). hit: (R,) bool.
        n_coarse, n_fine: samples per ray. background: 0 (black) or 1 (white).
        randomized: jittered strata and random inverse-CDF draws (training); False is deterministic.
        uniforms: optional ((R, n_coarse), (R, n_fine)) draws in [0, 1) for every ray, used instead of the
            generator, so that a ray's samples do not depend on which other rays share its batch (data-parallel
            fits render disjoint shares of one global batch).
        proposal_fn: optional ``(points (R', S, 3), ray_ids) -> sigma (R', S)`` that stands in for the field's density
            in the coarse pass (the occupancy grid's, :func:`bind_grid_proposal`): the importance samples then
            follow it, and the final pass still evaluates the coarse and fine samples with the field.
    """
    check_shape("origins", origins, (-1, 3))
    dtype, device = origins.dtype, origins.device
    ids = hit.nonzero()[:, 0]
    if ids.numel() == 0:
        return _place(origins, ids, None, None, None, background)
    o, d, t_near, t_far = origins[ids], dirs[ids], near[ids], far[ids]

    def rand(which: int, n: int):
        if not randomized:
            return None
        if uniforms is not None:
            return uniforms[which][ids]
        return torch.rand(ids.numel(), n, dtype=dtype, device=device, generator=generator)

    with torch.no_grad():
        coarse = stratified_depths(t_near, t_far, n_coarse, rand(0, n_coarse))
        coarse_points = o[:, None] + coarse[..., None] * d[:, None]
        if proposal_fn is None:
            coarse_sigma = field_fn(coarse_points, ids).sigma
        else:
            coarse_sigma = proposal_fn(coarse_points, ids)
        coarse_weights = weights_from_density(coarse_sigma, coarse, t_far)
        edges = torch.cat([coarse, t_far[:, None]], dim=-1)
        fine = importance_depths(edges, coarse_weights, n_fine, rand(1, n_fine)) if n_fine else coarse[:, :0]
        depths = torch.sort(torch.cat([coarse, fine], dim=-1), dim=-1).values
    out = field_fn(o[:, None] + depths[..., None] * d[:, None], ids)
    return _place(origins, ids, out, depths, t_far, background)


def _place(origins: torch.Tensor, ids: torch.Tensor, out, depths, far, background: float) -> RenderOutput:
    """Composite the samples of the rays ``ids`` (FieldOutput ``out`` at ``depths`` (R', K), ``far`` (R',)) and place
    them among all R rays (``origins`` (R, 3)); the others (all, when ``out`` is None) are misses: C = bg, M = 0."""
    n_rays, dtype, device = origins.shape[0], origins.dtype, origins.device
    rgb = torch.full((n_rays, 3), float(background), dtype=dtype, device=device)
    mask = torch.zeros(n_rays, dtype=dtype, device=device)
    depth = torch.zeros(n_rays, dtype=dtype, device=device)
    if out is None:
        return RenderOutput(rgb, mask, depth, None)
    weights = weights_from_density(out.sigma, depths, far)
    rgb_hit, mask_hit, depth_hit = composite(weights, out.rgb, depths, background)
    rgb, mask, depth = (
        rgb.index_put((ids,), rgb_hit),
        mask.index_put((ids,), mask_hit),
        depth.index_put((ids,), depth_hit),
    )
    part_weights = None
    if out.part_probs is not None:
        part_weights = torch.zeros(n_rays, out.part_probs.shape[-1], dtype=dtype, device=device)
        part_weights = part_weights.index_put((ids,), (weights[..., None] * out.part_probs).sum(dim=1))
    return RenderOutput(rgb, mask, depth, part_weights, weights, ids)


@torch.no_grad()
def render_rays_inference(
    field_fn: Callable,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    near: torch.Tensor,
    far: torch.Tensor,
    hit: torch.Tensor,
    n_coarse: int,
    n_fine: int,
    background: float = 0.0,
) -> RenderOutput:
    """Deterministic inference path of :func:`render_rays` (docs/model.md §5, "Inference renders"): the same coarse
    and fine depths, but the final pass reuses the coarse pass's outputs and evaluates only the Nf fine samples,
    so each ray costs Nc + Nf field samples instead of 2 Nc + Nf. Outputs equal ``render_rays(...,
    randomized=False)`` up to rounding (the field sees the samples in other batches).

    Args:
        as :func:`render_rays`. Returns a RenderOutput.
    """
    check_shape("origins", origins, (-1, 3))
    ids = hit.nonzero()[:, 0]
    if ids.numel() == 0:
        return _place(origins, ids, None, None, None, background)
    o, d, t_far = origins[ids], dirs[ids], far[ids]
    depths = stratified_depths(near[ids], t_far, n_coarse)
    out = field_fn(o[:, None] + depths[..., None] * d[:, None], ids)
    if n_fine:
        edges = torch.cat([depths, t_far[:, None]], dim=-1)
        fine = importance_depths(edges, weights_from_density(out.sigma, depths, t_far), n_fine)
        fine_out = field_fn(o[:, None] + fine[..., None] * d[:, None], ids)
        depths, order = torch.sort(torch.cat([depths, fine], dim=-1), dim=-1)
        out = FieldOutput(*(_merge(a, b, order) for a, b in zip(vars(out).values(), vars(fine_out).values())))
    return _place(origins, ids, out, depths, t_far, background)


def _merge(coarse: torch.Tensor | None, fine: torch.Tensor | None, order: torch.Tensor) -> torch.Tensor | None:
    """cat([coarse, fine], dim=1) reordered along dim 1 by ``order`` (R, Nc + Nf); values (R, N, ...)."""
    if coarse is None:
        return None
    values = torch.cat([coarse, fine], dim=1)
    index = order.reshape(*order.shape, *(1,) * (values.dim() - 2)).expand(*order.shape, *values.shape[2:])
    return values.gather(1, index)


def bind_field(field, dirs: torch.Tensor, pose, frame_of_ray: torch.Tensor, latent: torch.Tensor | None = None):
    """Adapt a field module to ``field_fn``: gathers each ray's direction, pose (``pose.select``) and latent."""

    def field_fn(points: torch.Tensor, ray_ids: torch.Tensor):
        frames = frame_of_ray[ray_ids]
        # index_select, not latent[frames]: its backward (index_add) sums the many rays of one code in a fixed
        # order on CPU, so autoencoder fits are bit-reproducible and resume exactly
        return field(
            points, dirs[ray_ids], pose.select(frames), None if latent is None else latent.index_select(0, frames)
        )

    return field_fn


def bind_grid_proposal(field, pose, frame_of_ray: torch.Tensor):
    """A ``proposal_fn`` for :func:`render_rays`: the density of the field's occupancy grid
    (:func:`narf.occupancy.grid_density`) at the samples, posed as :func:`bind_field` poses them."""

    def proposal_fn(points: torch.Tensor, ray_ids: torch.Tensor) -> torch.Tensor:
        ray_pose = pose.select(frame_of_ray[ray_ids])
        u = part_box_coordinates(points, ray_pose, field.box_centres, field.box_half_extents)
        return grid_density(field.occupancy, u)

    return proposal_fn


@torch.no_grad()
def image_ray_bounds(field, origins: torch.Tensor, dirs: torch.Tensor, pose, chunk: int = 1024):
    """:func:`narf.occupancy.field_ray_bounds` of all rays of one frame, computed only for the rays that cross the
    world box around all posed part boxes (padded by 1e-3 of its size against rounding); the others miss every
    box. Same results as calling ``field_ray_bounds`` on every ray, at a fraction of the cost when the body covers
    a small part of the image.

    Args:
        field: a Field. origins, dirs: (R, 3). pose: PoseBatch (its first frame is used). chunk: rays per bounds
            call.

    Returns:
        near (R,), far (R,), hit (R,) bool.
    """
    first = pose.select(torch.zeros(1, dtype=torch.long, device=origins.device))  # the frame render_image renders
    low, high = posed_box_bounds(first, field.box_centres, field.box_half_extents).to(origins.dtype)
    n_rays = origins.shape[0]
    one_box = torch.eye(4, dtype=origins.dtype, device=origins.device).expand(n_rays, 1, 4, 4)
    centre, half = (low + high)[None] / 2, (high - low)[None] / 2 * (1 + 1e-3)
    reach = torch.ones(n_rays, dtype=origins.dtype, device=origins.device)
    candidates = ray_box_intersect(origins, dirs, one_box, reach, centre, half)[2].nonzero()[:, 0]
    near, far = torch.zeros_like(origins[:, 0]), torch.zeros_like(origins[:, 0])
    hit = torch.zeros(n_rays, dtype=torch.bool, device=origins.device)
    frames = torch.zeros(n_rays, dtype=torch.long, device=origins.device)
    for start in range(0, candidates.numel(), chunk):
        ids = candidates[start : start + chunk]
        near[ids], far[ids], hit[ids] = field_ray_bounds(field, origins[ids], dirs[ids], pose.select(frames[ids]))
    return near, far, hit


@torch.no_grad()
def render_image(
    field,
    K: torch.Tensor,
    cam_from_world: torch.Tensor,
    height: int,
    width: int,
    pose,
    n_coarse: int = 64,
    n_fine: int = 128,
    background: float = 0.0,
    chunk: int = 1024,
    latent: torch.Tensor | None = None,
    reference: bool = False,
) -> dict[str, torch.Tensor]:
    """Render a full image of one frame, deterministically: ray bounds for every pixel, then the rays that hit
    (compacted) in chunks of ``chunk`` rays (bounded memory).

    Args:
        field: a Field module. K, cam_from_world: undistorted camera. pose: PoseBatch with one frame.
        latent: optional (1, 2 * latent_dim).
        reference: render with the reference :func:`render_rays` instead of :func:`render_rays_inference` (the
            same outputs up to rounding, one more evaluation of the coarse samples).

    Returns:
        rgb (H, W, 3), mask (H, W), depth (H, W), segmentation (H, W) long (-1 = background; only for part models).
    """
    device = next(field.parameters()).device
    dtype = next(field.parameters()).dtype
    pixels = image_pixels(height, width, device=device, dtype=dtype)
    origins, dirs = rays_from_pixels(K.to(device, dtype), cam_from_world.to(device, dtype), pixels)
    pose = pose.to(device)
    n_pixels = pixels.shape[0]
    frames = torch.zeros(n_pixels, dtype=torch.long, device=device)
    near, far, hit = image_ray_bounds(field, origins, dirs, pose, chunk)  # outside inference mode: it fills caches
    # inference mode (no autograd bookkeeping at all) for the field passes only; the images are cloned out of it so
    # that callers get ordinary tensors
    with torch.inference_mode():
        outputs = {
            "rgb": torch.full((n_pixels, 3), float(background), dtype=dtype, device=device),
            "mask": torch.zeros(n_pixels, dtype=dtype, device=device),
            "depth": torch.zeros(n_pixels, dtype=dtype, device=device),
            "segmentation": torch.full((n_pixels,), -1, dtype=torch.long, device=device),
        }
        hit_ids = hit.nonzero()[:, 0]
        for start in range(0, hit_ids.numel(), chunk):
            ids = hit_ids[start : start + chunk]
            o, d, all_hit = origins[ids], dirs[ids], torch.ones_like(ids, dtype=torch.bool)
            field_fn = bind_field(field, d, pose, frames[ids], latent)
            args = (field_fn, o, d, near[ids], far[ids], all_hit, n_coarse, n_fine, background)
            result = render_rays(*args, randomized=False) if reference else render_rays_inference(*args)
            outputs["rgb"][ids], outputs["mask"][ids], outputs["depth"][ids] = result.rgb, result.mask, result.depth
            if result.part_weights is not None:
                outputs["segmentation"][ids] = result.segmentation()
    if field.n_parts == 1:
        del outputs["segmentation"]
    return {k: v.reshape(height, width, *v.shape[1:]).clone() for k, v in outputs.items()}
