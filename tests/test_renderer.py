import math

import pytest
import torch
from kornia.geometry.linalg import inverse_transformation as invert_rigid
from kornia.geometry.linalg import transform_points

from narf.fields import FieldOutput
from narf.geometry import se3_exp
from narf.rays import image_pixels, ray_box_intersect, rays_from_pixels
from narf.renderer import composite, render_rays, render_rays_inference, weights_from_density
from narf.sampling import importance_depths, stratified_depths


def test_compositing_hand_computed():
    sigmas = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    depths = torch.tensor([[1.0, 1.5]], dtype=torch.float64)
    far = torch.tensor([2.5], dtype=torch.float64)
    weights = weights_from_density(sigmas, depths, far)
    a0, a1 = 1 - math.exp(-1.0 * 0.5), 1 - math.exp(-2.0 * 1.0)
    # float64 against the same formula by hand: a handful of operations, ~1e-16; allclose's defaults below as well
    assert torch.allclose(weights, torch.tensor([[a0, (1 - a0) * a1]], dtype=torch.float64), atol=1e-9)
    colours = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]], dtype=torch.float64)
    rgb, mask, depth = composite(weights, colours, depths, 1.0)
    m = a0 + (1 - a0) * a1
    assert torch.allclose(rgb, torch.tensor([[a0 + 1 - m, (1 - a0) * a1 + 1 - m, 1 - m]], dtype=torch.float64))
    assert math.isclose(mask.item(), m, rel_tol=1e-9)
    assert math.isclose(depth.item(), a0 * 1.0 + (1 - a0) * a1 * 1.5, rel_tol=1e-9)


def test_compositing_gradcheck():
    sig = torch.rand(3, 5, dtype=torch.float64, requires_grad=True)
    col = torch.rand(3, 5, 3, dtype=torch.float64, requires_grad=True)
    depths = torch.sort(torch.rand(3, 5, dtype=torch.float64), dim=-1).values
    far = torch.full((3,), 1.5, dtype=torch.float64)
    assert torch.autograd.gradcheck(
        lambda s, c: composite(weights_from_density(s, depths, far), c, depths, 0.0)[0], (sig, col)
    )


def test_ray_box_against_brute_force():
    gen = torch.Generator().manual_seed(0)
    n_rays, n_parts = 300, 3
    origins = torch.randn(n_rays, 3, generator=gen, dtype=torch.float64) * 3
    targets = torch.randn(n_rays, 3, generator=gen, dtype=torch.float64) * 0.5
    dirs = (targets - origins) / (targets - origins).norm(dim=1, keepdim=True)
    dirs[:5] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)  # axis-aligned rays: zero direction components
    world_from_part = se3_exp(torch.randn(n_parts, 6, generator=gen, dtype=torch.float64) * 0.5)
    centres = torch.randn(n_parts, 3, generator=gen, dtype=torch.float64) * 0.2
    half = torch.rand(n_parts, 3, generator=gen, dtype=torch.float64) * 0.4 + 0.1
    reach = torch.full((n_rays,), 1.3, dtype=torch.float64)
    near, far, hit = ray_box_intersect(origins, dirs, world_from_part.expand(n_rays, -1, -1, -1), reach, centres, half)
    ts = torch.linspace(0, 12, 24001, dtype=torch.float64)
    points = origins[:, None] + ts[None, :, None] * dirs[:, None]  # (R, T, 3)
    local = transform_points(invert_rigid(world_from_part), points.reshape(1, -1, 3).expand(n_parts, -1, -1))
    inside = (((local / 1.3 - centres[:, None]) / half[:, None]).abs().amax(-1) <= 1).any(0).reshape(n_rays, -1)
    assert torch.equal(inside.any(1), hit)
    first = torch.where(inside, ts, torch.inf).amin(1)
    last = torch.where(inside, ts, -torch.inf).amax(1)
    step = 12 / 24000
    assert (near[hit] - first[hit]).abs().max() <= step + 1e-9
    assert (far[hit] - last[hit]).abs().max() <= step + 1e-9
    assert (near[~hit] == 0).all() and (far[~hit] == 0).all()


def test_sampling():
    near, far = torch.tensor([1.0, 2.0]), torch.tensor([3.0, 2.5])
    t = stratified_depths(near, far, 4)
    assert torch.allclose(t[0], torch.tensor([1.25, 1.75, 2.25, 2.75]))  # exact binary fractions
    edges = torch.linspace(0, 1, 6).expand(2, 6)
    weights = torch.tensor([[0, 0, 1.0, 0, 0], [1.0, 1.0, 1.0, 1.0, 1.0]])
    samples = importance_depths(edges, weights, 1000)
    # float32 edges from linspace: 0.4 and 0.6 are inexact in binary, so allow eps32-scale slack (1e-6)
    assert ((samples[0] >= 0.4 - 1e-6) & (samples[0] <= 0.6 + 1e-6)).float().mean() > 0.99
    hist = torch.histc(samples[1], bins=5, min=0, max=1)
    # 1000 evenly spaced quantiles of a uniform pdf: 200 per bin, +-1 where a quantile lands on a bin edge
    assert torch.allclose(hist, torch.full((5,), 200.0), atol=2)


def test_rays_from_pixels_hit_their_pixels():
    K = torch.tensor([[100.0, 0, 32], [0, 100.0, 30], [0, 0, 1]], dtype=torch.float64)
    cam_from_world = se3_exp(torch.tensor([0.1, -0.2, 0.3, 0.5, 0.1, 2.0], dtype=torch.float64))
    pixels = image_pixels(8, 9, dtype=torch.float64)
    origins, dirs = rays_from_pixels(K, cam_from_world, pixels)
    points = origins + 2.7 * dirs
    cam = transform_points(cam_from_world, points)
    projected = (cam @ K.T)[:, :2] / cam[:, 2:]
    # float64 unprojection and projection at 2.7 m with f = 100: ~20 operations on values ~100, ~1e-12 px
    assert torch.allclose(projected, pixels, atol=1e-9)


def test_render_rays_of_a_constant_field_hand_computed():
    """A slab of constant density between near and far: M = 1 - exp(-sigma (far - near))."""
    sigma = 0.7

    def field_fn(points, ray_ids):
        r, s, _ = points.shape
        dtype = points.dtype
        return FieldOutput(torch.full((r, s), sigma, dtype=dtype), torch.full((r, s, 3), 0.5, dtype=dtype))

    origins = torch.zeros(3, 3, dtype=torch.float64)
    dirs = torch.tensor([[0, 0, 1.0]] * 3, dtype=torch.float64)
    near, far = torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64), torch.tensor([2.0, 3.0, 0.0], dtype=torch.float64)
    hit = torch.tensor([True, True, False])
    out = render_rays(
        field_fn,
        origins,
        dirs,
        near,
        far,
        hit,
        8,
        8,
        background=1.0,
        randomized=True,
        generator=torch.Generator().manual_seed(0),
    )
    expected = 1 - torch.exp(-sigma * (far - torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64)))
    # the first sample lies after near: the skipped piece [near, t_0] is at most one stratum
    assert (out.mask[:2] - expected[:2]).abs().max() < 1 - math.exp(-sigma * 2 / 8)
    assert out.mask[2] == 0 and torch.allclose(out.rgb[2], torch.ones(3, dtype=torch.float64))
    # float64 compositing of 16 samples: ~16 eps64
    assert torch.allclose(out.rgb[:2], 0.5 * out.mask[:2, None] + (1 - out.mask[:2, None]), atol=1e-9)


def test_render_rays_rejects_bad_shapes():
    with pytest.raises(ValueError, match="origins"):
        render_rays(
            None, torch.zeros(3), torch.zeros(3), torch.zeros(1), torch.zeros(1), torch.ones(1, dtype=bool), 4, 4
        )


def _shells_field(evaluated: list):
    """Two concentric shells about the origin (sigma 200 for 0.4 <= |x| <= 0.5, 3 for 0.8 <= |x| <= 0.9), colour
    and part probabilities varying with the point; float64. Appends the number of evaluated samples to
    ``evaluated``."""

    def field_fn(points, ray_ids):
        evaluated.append(points.shape[0] * points.shape[1])
        radius = points.norm(dim=-1)
        sigma = torch.where((radius >= 0.4) & (radius <= 0.5), 200.0, 0.0)
        sigma = sigma + torch.where((radius >= 0.8) & (radius <= 0.9), 3.0, 0.0)
        return FieldOutput(sigma.to(points.dtype), torch.sigmoid(points * 3), torch.softmax(points, dim=-1))

    return field_fn


@pytest.mark.parametrize("n_fine", [0, 16])
def test_inference_render_is_the_reference_with_fewer_evaluations(n_fine):
    """render_rays_inference reuses the coarse outputs in the final pass: the deterministic reference's outputs
    with Nc + Nf instead of 2 Nc + Nf samples per hit ray."""
    n = 64
    generator = torch.Generator().manual_seed(3)
    offsets = torch.rand(n, 2, generator=generator, dtype=torch.float64) * 1.6 - 0.8
    origins = torch.cat([offsets, torch.full((n, 1), -2.0, dtype=torch.float64)], dim=-1)
    dirs = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(n, 3)
    near, far = torch.full((n,), 1.0, dtype=torch.float64), torch.full((n,), 3.0, dtype=torch.float64)
    hit = torch.arange(n) >= 4
    reference_count, inference_count = [], []
    reference = render_rays(_shells_field(reference_count), origins, dirs, near, far, hit, 16, n_fine, 1.0, False)
    inference = render_rays_inference(_shells_field(inference_count), origins, dirs, near, far, hit, 16, n_fine, 1.0)
    # float64, the same samples through the same arithmetic: ~1e-15
    for key in ("rgb", "mask", "depth", "part_weights"):
        assert torch.allclose(getattr(inference, key), getattr(reference, key), rtol=0, atol=1e-12), key
    assert sum(reference_count) == 60 * (16 + 16 + n_fine) and sum(inference_count) == 60 * (16 + n_fine)
    assert reference.mask.max() > 0.99  # the inner shell is opaque: the test composites real surfaces
