import dataclasses
import math

import pytest
import torch
from kornia.geometry.linalg import inverse_transformation as invert_rigid
from kornia.geometry.linalg import transform_points

from narf.encodings import frequency_window, positional_encoding, windowed
from narf.fields import PoseBatch, build_field, model_names, paper_presets, paper_rows
from narf.fields.base import masked_softmax, rescale_selection
from narf.fields.common import colour_from_nearest_place, part_box_coordinates, part_directions, part_local
from narf.geometry import se3_exp
from narf.layers import EqualLinear, WNLinear, leaky_backward_relu, scaled_unit_rows
from narf.renderer import render_image

torch.set_default_dtype(torch.float32)


def _random_pose(n_frames=1, n_parts=19, seed=0, dtype=torch.float32):
    gen = torch.Generator().manual_seed(seed)
    xi = torch.randn(n_frames, n_parts, 6, generator=gen) * 0.3
    world_from_part = se3_exp(xi).to(dtype)
    zeta = torch.rand(n_frames, 19, generator=gen).to(dtype)
    return PoseBatch(
        world_from_part,
        torch.ones(n_frames, dtype=dtype),
        zeta,
        (xi * 0.5).to(dtype),
        (torch.randn(n_frames, n_parts, 3, generator=gen) * 0.2).to(dtype),
    )


def _field(name, width=16, n_parts=19, dtype=torch.float32, **kwargs):
    torch.manual_seed(0)
    field = build_field(name, width=width, **kwargs)
    field.set_boxes(torch.zeros(field.n_parts, 3), torch.full((field.n_parts, 3), 0.6))
    return field.to(dtype)


def _points(n_rays=4, n_samples=6, seed=1, dtype=torch.float32):
    gen = torch.Generator().manual_seed(seed)
    points = (torch.rand(n_rays, n_samples, 3, generator=gen) * 2 - 1).to(dtype)
    dirs = torch.randn(n_rays, 3, generator=gen).to(dtype)
    return points, dirs / dirs.norm(dim=1, keepdim=True)


@pytest.mark.parametrize("name", model_names("field", "rigid"))
def test_every_model_runs_and_masks_outside_boxes(name):
    field = _field(name)
    points, dirs = _points()
    points[0, 0] = 50.0  # far outside every box
    pose = _random_pose(n_parts=field.n_parts).select(torch.zeros(4, dtype=torch.long))
    out = field(points, dirs, pose)
    assert out.sigma.shape == (4, 6) and out.rgb.shape == (4, 6, 3)
    assert (out.sigma >= 0).all() and ((out.rgb >= 0) & (out.rgb <= 1)).all()
    assert out.sigma[0, 0] == 0
    latent_field = (
        build_field(name, width=16, latent_dim=8)
        if name not in ("rt_nerf", "rt_nerf_no_pose", "rp_nerf")
        else build_field(name, width=16, latent_dim=8)
    )
    latent_field.set_boxes(torch.zeros(latent_field.n_parts, 3), torch.full((latent_field.n_parts, 3), 0.6))
    z = torch.randn(4, 16)
    # the latent moves colours by O(0.1); allclose's defaults (float32 rounding scale) only guard against no change
    assert not torch.allclose(latent_field(points, dirs, pose, z).rgb, latent_field(points, dirs, pose, -z).rgb)


@pytest.mark.parametrize("name, reference", sorted((row.key, row.cost) for _, row in paper_rows() if row.cost))
def test_paper_costs_within_five_percent(name, reference):
    cost = paper_presets()[name].cost()
    # the tables print three significant digits and upstream counts a few small terms differently (docs/model.md §8)
    for ours, theirs in zip((cost.params, cost.flops_per_ray, cost.memory_per_ray), reference):
        assert abs(ours / theirs - 1) < 0.05, (name, ours, theirs)


def test_selector_size_and_probabilities():
    field = _field("narf_d")
    # the paper quotes the selector as "about 41k" (two significant digits)
    assert sum(p.numel() for p in field.selector.parameters()) == pytest.approx(41_000, rel=0.02)
    logits = torch.randn(5, 7, 19)
    mask = torch.rand(5, 7, 19) > 0.6
    mask[0, 0] = False
    probs = masked_softmax(logits, mask)
    has = mask.any(-1)
    # float32 sum of <= 19 probabilities: pairwise summation error <= log2(19) eps32 ~ 6e-7
    assert torch.allclose(probs.sum(-1)[has], torch.ones(int(has.sum())), atol=1e-6)
    assert (probs[~mask] == 0).all() and (probs[0, 0] == 0).all()
    rescaled = rescale_selection(probs)
    # float32 norm, division and product at magnitude sqrt(19) ~ 4.4: a few eps32 relative (~2e-6); a wrong rescale
    # is off by O(1)
    assert torch.allclose(rescaled.norm(dim=-1)[has], torch.full((int(has.sum()),), math.sqrt(19)), atol=1e-4)


def test_layers():
    layer = WNLinear(5, 4, groups=3)
    # float32 norm of 5 values after a division by that norm: a few eps32, inside allclose's default rtol 1e-5
    assert torch.allclose(layer.effective_weight().norm(dim=2), torch.ones(3, 4))
    x = torch.randn(3, 10, 5)
    reference = torch.stack(
        [torch.nn.functional.linear(x[g], layer.effective_weight()[g], layer.bias[g, 0]) for g in range(3)]
    )
    # grouped fast path vs per-group loop: float32 dot products of 5 terms summed in another order, error
    # <= 5 eps32 sum|x_i w_i| (unit-norm rows, |x| ~ 2: about 1.2e-6 at worst)
    assert torch.allclose(layer(x), reference, atol=1e-5)
    eq = EqualLinear(16, 2)
    assert torch.allclose(eq.effective_weight(), eq.weight / 4)  # 1/sqrt(16) = 0.25: exact in binary
    a = torch.tensor([-1.0, -1.0, 2.0], requires_grad=True)
    leaky_backward_relu(a).backward(torch.tensor([-1.0, 1.0, 3.0]))
    assert torch.equal(a.grad, torch.tensor([-0.1, 0.0, 3.0]))  # negative pre-activations can only rise


def test_scaled_unit_rows_matches_autograd():
    """The hand-written backward against autograd of s x / max(|x|, eps), float64, with rows above and below eps
    (where the clamp holds the norm and the gradient is s g / eps)."""
    torch.manual_seed(0)
    x = torch.randn(6, 8, dtype=torch.float64)
    x[1] *= 1e-8  # |x| ~ 3e-8 < eps: the clamped branch
    grad = torch.randn(6, 8, dtype=torch.float64)
    a, b = x.clone().requires_grad_(), x.clone().requires_grad_()
    ours = scaled_unit_rows(a, 8.0, 1e-6)
    reference = 8.0 * b / b.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    ours.backward(grad)
    reference.backward(grad)
    # float64, a dozen operations per element on O(1) values (O(s/eps) = 8e6 in the clamped row): ~1e-15 relative
    assert torch.allclose(ours, reference, rtol=1e-12, atol=0)
    assert torch.allclose(a.grad, b.grad, rtol=1e-12, atol=0)
    assert torch.autograd.gradcheck(lambda t: scaled_unit_rows(t, 3.0, 1e-6), (x[[0, 2]].clone().requires_grad_(),))


def test_in_box_pairs_are_the_nonzeros_stably_sorted_by_part():
    from narf.fields.sparse_parts import in_box_pairs

    torch.manual_seed(0)
    in_box = torch.rand(7, 5, 4) < 0.3
    pairs = in_box.nonzero()
    expected = pairs[torch.argsort(pairs[:, 2], stable=True)].unbind(-1)
    assert all(torch.equal(a, b) for a, b in zip(in_box_pairs(in_box), expected))


def test_part_local_matches_loop():
    pose = _random_pose(n_frames=3, n_parts=4)
    points, dirs = _points(3, 5)
    x_local, d_local = part_local(points, dirs, pose)
    for r in range(3):
        for p in range(4):
            part_from_world = invert_rigid(pose.world_from_part[r, p])
            # float32 rigid transform: a 3-term dot product plus a translation on coordinates <= ~3, so a few
            # eps32 * 3 ~ 1.5e-6; directions are unit vectors (3 eps32 ~ 4e-7)
            assert torch.allclose(
                x_local[r, :, p], transform_points(part_from_world, points[r]) / pose.reach[r], atol=1e-5
            )
            assert torch.allclose(d_local[r, p], part_from_world[:3, :3] @ dirs[r], atol=1e-6)
    with torch.autocast("cpu", dtype=torch.bfloat16):  # the bf16 switch must not round the coordinates
        x_auto, d_auto = part_local(points, dirs, pose)
    assert x_auto.dtype == torch.float32 and torch.equal(x_auto, x_local) and torch.equal(d_auto, d_local)


def test_fused_box_coordinates_match_the_two_step_reference():
    """part_box_coordinates (one affine map per ray) against (part_local - c) / h, and float32 against float64."""
    pose = _random_pose(n_frames=3, n_parts=4, dtype=torch.float64)
    points, dirs = _points(3, 5, dtype=torch.float64)
    shift = torch.tensor([2.5, -3.0, 1.0], dtype=torch.float64)  # a capture's world origin is metres from the body
    points = points + shift
    pose.world_from_part[..., :3, 3] += shift
    centres = torch.randn(4, 3, dtype=torch.float64) * 0.2
    half = torch.rand(4, 3, dtype=torch.float64) * 0.3 + 0.05
    reference = (part_local(points, dirs, pose)[0] - centres) / half
    fused = part_box_coordinates(points, pose, centres, half)
    # float64, a dozen operations on values <= ~3 / 0.05: ~1e-13
    assert torch.allclose(fused, reference, rtol=0, atol=1e-10)
    assert torch.allclose(part_directions(dirs, pose), part_local(points, dirs, pose)[1], rtol=0, atol=1e-12)
    pose32 = PoseBatch(
        *(
            v.float()
            for v in (pose.world_from_part, pose.reach, pose.bone_lengths, pose.pose_features, pose.rest_offsets)
        )
    )
    fused32 = part_box_coordinates(points.float(), pose32, centres.float(), half.float())
    # float32: coordinates ~2 relative to the anchor, rounding ~2 * 6e-8 per operation, divided by h >= 0.05:
    # ~1e-5; gamma_10 needs u to ~1e-4 (its top frequency is 2^9 pi)
    assert (fused32.double() - reference).abs().max() < 1e-4
    with torch.autocast("cpu", dtype=torch.bfloat16):  # the bf16 switch must not round the coordinates
        assert part_box_coordinates(points.float(), pose32, centres.float(), half.float()).dtype == torch.float32


@pytest.mark.parametrize("name", ["narf_d", "narf_p", "d_narf", "p_nerf"])
def test_gradcheck_small_fields(name):
    field = _field(name, width=4, dtype=torch.float64, density_act="softplus")
    points, dirs = _points(2, 3, dtype=torch.float64)
    pose = _random_pose(n_parts=19, dtype=torch.float64).select(torch.zeros(2, dtype=torch.long))
    points.requires_grad_(True)

    def fn(p):
        out = field(p, dirs, pose)
        return out.sigma, out.rgb

    # gamma_10 has frequencies up to 2^9 pi: Jacobian entries reach 1e3-1e4, so compare relatively
    assert torch.autograd.gradcheck(fn, (points,), eps=1e-7, atol=1e-4, rtol=1e-3)


@pytest.mark.parametrize("name", ["narf_d", "narf_h", "narf_p", "d_narf"])
def test_rigid_motion_of_body_and_camera_leaves_pixels_unchanged(name):
    # float64: in float32 the box edges and the inverse-CDF sampler turn rounding into visible differences
    dt = torch.float64
    field = _field(name, width=16, dtype=dt)
    pose = _random_pose(dtype=dt)
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]], dtype=dt)
    cam_from_world = se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 4.0], dtype=dt))
    motion = se3_exp(torch.tensor([0.4, -0.7, 0.2, 1.0, -2.0, 0.5], dtype=dt))
    moved = PoseBatch(
        motion @ pose.world_from_part, pose.reach, pose.bone_lengths, pose.pose_features, pose.rest_offsets
    )
    a = render_image(field, K, cam_from_world, 32, 32, pose, n_coarse=8, n_fine=8)
    b = render_image(field, K, cam_from_world @ invert_rigid(motion), 32, 32, moved, n_coarse=8, n_fine=8)
    assert a["mask"].max() > 0.01
    # Only the order of the rigid products differs, so a and b differ by rounding: float64 eps (2.2e-16) on
    # coordinates of a few units, amplified by the field's spatial derivative and again by the importance sampler,
    # whose fine depths follow the coarse weights (docs/model.md §5). |dsigma/dx| reaches ~1e3 for NARF_D/H/P
    # (renders differ by <= 1e-9) and ~1e5 for D-NARF, whose blended coordinate re-encodes the selector's output
    # with 10 frequencies (docs/model.md §4; renders differ by ~1e-6). A geometric error is of another order:
    # moving the camera by 0.1 mm changes pixels by more than 1e-2 (the control below). 1e-4 separates the two.
    tolerance = 1e-4
    for key in ("rgb", "mask", "depth"):
        assert torch.allclose(a[key], b[key], atol=tolerance), key
    shifted = cam_from_world.clone()
    shifted[0, 3] += 1e-4
    c = render_image(field, K, shifted, 32, 32, pose, n_coarse=8, n_fine=8)
    assert (a["mask"] - c["mask"]).abs().max() > 100 * tolerance


def _density_change(field, part, points, dirs):
    pose = _random_pose()
    changed = PoseBatch(
        pose.world_from_part.clone(), pose.reach, pose.bone_lengths, pose.pose_features, pose.rest_offsets
    )
    changed.world_from_part[0, part] = changed.world_from_part[0, part] @ se3_exp(
        torch.tensor([0.0, 0.5, 0.3, 0.1, 0.0, 0.0])
    )
    frames = torch.zeros(points.shape[0], dtype=torch.long)
    before, after = pose.select(frames), changed.select(frames)
    with torch.no_grad():
        delta = (field(points, dirs, before).sigma - field(points, dirs, after).sigma).abs()
    in_box_before = field.box_coordinates(part_local(points, dirs, before)[0])[1]
    in_box_after = field.box_coordinates(part_local(points, dirs, after)[0])[1]
    return delta, in_box_before, in_box_after


@pytest.mark.parametrize("name", ["narf_d", "narf_p", "narf_h"])
def test_changing_one_part_changes_density_only_in_its_box(name):
    field = _field(name, width=16)
    field.set_boxes(torch.zeros(19, 3), torch.full((19, 3), 0.3))
    points, dirs = _points(64, 16, seed=3)
    delta, before, after = _density_change(field, 5, points, dirs)
    outside = ~before[..., 5] & ~after[..., 5]
    assert outside.sum() > 100 and (~outside).sum() > 10
    # outside part 5's box its input block is zero before and after: the density is mathematically unchanged, and
    # float32 rounding of sigma ~ 1 through a 16-wide network stays below 1e-6 (~8 eps32); inside the box a
    # 0.5 rad change of the part moves the density by O(0.1)
    assert delta[outside].max() < 1e-6
    assert delta[~outside].max() > 1e-4


def test_selector_gates_out_a_part_where_narf_h_cannot():
    """With part 5's selector logit pushed down, NARF_D's density ignores part 5 wherever another part's box also
    contains the point; NARF_H (no selector) changes throughout part 5's box."""
    narf_d, narf_h = _field("narf_d", width=16), _field("narf_h", width=16)
    for field in (narf_d, narf_h):
        field.set_boxes(torch.zeros(19, 3), torch.full((19, 3), 0.3))
    with torch.no_grad():
        narf_d.selector.out.bias[5] = -40.0
    points, dirs = _points(64, 16, seed=3)
    delta_d, before, after = _density_change(narf_d, 5, points, dirs)
    delta_h, _, _ = _density_change(narf_h, 5, points, dirs)
    others = torch.cat([before[..., :5], before[..., 6:]], -1).any(-1) & torch.cat(
        [after[..., :5], after[..., 6:]], -1
    ).any(-1)
    shared = (before[..., 5] | after[..., 5]) & others
    assert shared.sum() > 10
    # NARF_D's weight for part 5 is ~e^-40 there, so only float32 rounding remains (< 1e-6 on sigma ~ 1); the bound
    # 1e-4 sits an order below NARF_H's change
    assert delta_d[shared].max() < 1e-4
    assert delta_h[shared].max() > 1e-3


def test_bad_inputs():
    field = _field("narf_d")
    points, dirs = _points()
    with pytest.raises(ValueError, match="pose: expected 4 per-ray entries of 19 parts"):
        field(points, dirs, _random_pose())
    with pytest.raises(ValueError, match="unknown model"):
        build_field("narf_x")
    with pytest.raises(ValueError, match="selector"):
        build_field("narf_d", selector="max")
    with pytest.raises(ValueError, match="half-extents"):
        field.set_boxes(torch.zeros(19, 3), torch.zeros(19, 3))


@pytest.mark.parametrize("name", ["narf_d", "narf_d_sigmoid", "narf_h", "narf_p", "d_narf"])
def test_sparse_fast_path_matches_dense_reference(name, monkeypatch):
    monkeypatch.setattr("narf.fields.narf_p.PACKED_SHARE", 1.0)  # NARF_P: always the packed pass, never the dense
    fast = _field(name, width=16, dtype=torch.float64, latent_dim=4)
    dense = _field(name, width=16, dtype=torch.float64, latent_dim=4)
    dense.load_state_dict(fast.state_dict())
    dense.fast = False
    # boxes of very different sizes: the parts hold very different sample counts (NARF_P packs ragged blocks)
    half_extents = torch.linspace(0.05, 0.8, 19, dtype=torch.float64)[:, None].expand(19, 3)
    fast.set_boxes(torch.zeros(19, 3, dtype=torch.float64), half_extents)
    dense.set_boxes(fast.box_centres, fast.box_half_extents)
    points, dirs = _points(8, 12, seed=5, dtype=torch.float64)
    points[0, :3] = 20.0  # samples outside every box
    pose = _random_pose(n_frames=2, dtype=torch.float64).select(torch.tensor([0, 1] * 4))
    latent = torch.randn(8, 8, dtype=torch.float64)
    points.requires_grad_(True)
    a, b = fast(points, dirs, pose, latent), dense(points, dirs, pose, latent)
    if name == "d_narf":  # its fast path skips the head where sigma = 0 (no render weighs that colour)
        inside = (b.part_probs.sum(-1) > 0)[..., None]
        assert inside.any() and not inside.all()
        a.rgb, b.rgb = torch.where(inside, a.rgb, 0.0), torch.where(inside, b.rgb, 0.0)
    # float64, the same sums in another order (per-part matmuls vs one wide matmul): ~1e3 operations on values
    # <= ~10 give ~1e-12; gradients pass through gamma_10 (derivatives up to 2^9 pi ~ 1.6e3), hence 1e-8 for them
    assert torch.allclose(a.sigma, b.sigma, atol=1e-10) and torch.allclose(a.rgb, b.rgb, atol=1e-10)
    assert torch.allclose(a.part_probs, b.part_probs, atol=1e-10)
    grad_a = torch.autograd.grad(a.sigma.sum() + a.rgb.sum(), [points, *fast.parameters()], allow_unused=True)
    grad_b = torch.autograd.grad(b.sigma.sum() + b.rgb.sum(), [points, *dense.parameters()], allow_unused=True)
    for ga, gb in zip(grad_a, grad_b):
        if ga is None or gb is None:
            assert (ga is None or ga.abs().max() == 0) and (gb is None or gb.abs().max() == 0)
        else:
            assert torch.allclose(ga, gb, atol=1e-8)


@pytest.mark.parametrize("name", ["narf_d", "narf_d_sigmoid"])
def test_the_fast_path_gathers_no_rows_by_advanced_indexing(name):
    """NARF_D's in-box path reads per-pair rows with index_select or per-part blocks, never ``x[index]``: on CUDA the
    gradient of advanced indexing sorts the indices and sums each row's pairs serially, which took a third of an
    H200's training step while the selector's 19 output rows were gathered once per pair (docs/results/benchmark.md,
    *A GPU step*). The graph of sigma and rgb must hold no IndexBackward0 node, with the poses refined too."""
    field = _field(name, width=16)
    points, dirs = _points(8, 12, seed=5)
    pose = _random_pose(n_frames=2)
    refined = dataclasses.replace(pose, world_from_part=pose.world_from_part.detach().requires_grad_(True))
    pose = refined.select(torch.tensor([0, 1] * 4))
    out = field(points, dirs, pose)
    names, stack, seen = set(), [(out.sigma.sum() + out.rgb.sum()).grad_fn], set()
    while stack:
        node = stack.pop()
        if node is not None and node not in seen:
            seen.add(node)
            names.add(type(node).__name__)
            stack.extend(next_node for next_node, _ in node.next_functions)
    assert "IndexSelectBackward0" in names  # the walk reaches the gathers
    assert "IndexBackward0" not in names


@pytest.mark.parametrize("name", [*model_names("field", "rigid"), "narf_d_dense"])
def test_density_alone_equals_the_forward_sigma(name):
    """Field.density (the occupancy refresh's query; NARF_D / NARF_H skip the colour branch) against the full
    forward's sigma: the same kernels on the same inputs, so equal to the bit; with an autoencoder latent, whose
    shape half enters the density (articulated models: autoencoders are of bodies)."""
    dense = name == "narf_d_dense"
    rigid = name in model_names("rigid")
    field = _field("narf_d" if dense else name, latent_dim=0 if rigid else 4)
    if dense:
        field.fast = False
    points, dirs = _points(8, 12, seed=5)
    points[0, :3] = 20.0  # outside every box: sigma 0
    pose = _random_pose(n_frames=2, n_parts=field.n_parts).select(torch.tensor([0, 1] * 4))
    latent = None if rigid else torch.randn(8, 8)
    with torch.no_grad():
        full, alone = field(points, dirs, pose, latent).sigma, field.density(points, dirs, pose, latent)
    assert alone.shape == (8, 12) and alone[0, :3].abs().max() == 0 and alone.abs().max() > 0
    assert torch.equal(alone, full)


def test_narf_p_packed_pass_without_in_box_samples(monkeypatch):
    monkeypatch.setattr("narf.fields.narf_p.PACKED_SHARE", 1.0)
    field = _field("narf_p")
    points, dirs = _points()
    out = field(points + 50.0, dirs, _random_pose().select(torch.zeros(4, dtype=torch.long)))
    assert out.sigma.abs().max() == 0 and out.part_probs.abs().max() == 0


def test_image_encoder_size_and_shapes():
    from narf.fields.encoder import ImageEncoder

    encoder = ImageEncoder()
    assert sum(p.numel() for p in encoder.parameters()) == pytest.approx(13.8e6, rel=0.01)  # "13.8M": 3 digits
    assert encoder(torch.rand(2, 3, 128, 128)).shape == (2, 512)
    with pytest.raises(ValueError, match=r"images: expected shape \(\*, 3, 128, 128\)"):
        encoder(torch.rand(2, 3, 64, 64))


def test_cost_cli_prints_every_model(capsys):
    from pipelines.cli.cost import main

    assert main([]) == 0
    table = capsys.readouterr().out
    assert "| NARF_D | 1.11M | 206M | 383K | 1.10M / 205M / 382K |" in table
    assert table.count("\n") == 3 + len(paper_presets())  # header, rule, models, CNN baseline
    assert main(["--model", "d_narf"]) == 0
    assert capsys.readouterr().out.count("D-NARF") == 1


def test_render_image_with_chunks_that_miss_every_box():
    field = _field("narf_d", width=8)
    field.set_boxes(torch.zeros(19, 3), torch.full((19, 3), 0.05))
    pose = _random_pose()
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    cam_from_world = se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 4.0]))
    out = render_image(field, K, cam_from_world, 32, 32, pose, n_coarse=4, n_fine=4, chunk=64)
    assert out["segmentation"].shape == (32, 32) and (out["segmentation"][:2] == -1).all()
    assert out["rgb"].shape == (32, 32, 3) and out["mask"][:2].max() == 0
    rigid = _field("rt_nerf", width=8)
    assert "segmentation" not in render_image(rigid, K, cam_from_world, 8, 8, _random_pose(n_parts=1), 4, 4)


@pytest.mark.parametrize("name", ["narf_d", "narf_h", "narf_p", "d_narf"])
def test_sparse_fast_path_with_every_sample_outside_the_boxes(name):
    """A batch that misses every box (mesh extraction queries such grid chunks): the same as the dense reference,
    zero density, and no empty-list failure."""
    fast, dense = _field(name, width=16), _field(name, width=16)
    dense.load_state_dict(fast.state_dict())
    dense.fast = False
    points, dirs = _points(4, 6, seed=1)
    far = points + 100.0
    pose = _random_pose().select(torch.zeros(4, dtype=torch.long))
    a, b = fast(far, dirs, pose), dense(far, dirs, pose)
    assert a.sigma.abs().max() == 0 and torch.equal(a.sigma, b.sigma)


@pytest.mark.parametrize("name", ["narf_d", "narf_h", "narf_p", "d_narf"])
def test_fast_paths_run_under_bf16_autocast(name):
    """train.precision=bf16 runs every fast path under autocast, where bfloat16 matmul outputs meet float32
    buffers in the scatters. Values are not compared with float32 here: a random-init field's outputs are sums of
    ~200 rounded products that cancel, so bfloat16's 8 bits give errors of the order of the outputs themselves; the
    benchmark measures training speed in bf16 and its fits measure quality."""
    field = _field(name, width=16)
    points, dirs = _points(4, 6, seed=2)
    points[0, 0] = 50.0  # outside every box
    pose = _random_pose().select(torch.zeros(4, dtype=torch.long))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = field(points, dirs, pose)
    assert out.sigma.shape == (4, 6) and out.rgb.shape == (4, 6, 3)
    assert torch.isfinite(out.sigma).all() and (out.sigma >= 0).all() and out.sigma[0, 0] == 0
    assert ((out.rgb >= 0) & (out.rgb <= 1)).all()


@pytest.mark.parametrize("name", ["narf_d", "narf_h"])
def test_the_per_part_loops_cast_once_under_autocast(name, monkeypatch):
    """Under bf16 autocast the per-part loops cast each operand once for every part (sparse_parts.matmul_dtype)
    instead of letting autocast cast each part's slice: the same roundings of the same values in the same layout,
    so sigma, rgb and every gradient (the parameters' and the refined poses') equal autocast's own per-part casts
    to the bit, in fewer cast kernels (docs/results/benchmark.md, *autocast's casts in the per-part loops*)."""
    from narf.fields import sparse_parts

    field = _field(name, width=16)
    points, dirs = _points(8, 12, seed=3)
    refined = _random_pose(n_frames=2).world_from_part.requires_grad_(True)  # the poses refined: u has a gradient

    def run():
        field.zero_grad()
        refined.grad = None
        pose = dataclasses.replace(_random_pose(n_frames=2), world_from_part=refined).select(torch.tensor([0, 1] * 4))
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = field(points, dirs, pose)
        (out.sigma.float().square().sum() + out.rgb.float().sum()).backward()
        grads = [p.grad.clone() for p in [refined, *field.parameters()] if p.grad is not None]
        with torch.autograd.profiler.profile() as prof, torch.autocast("cpu", dtype=torch.bfloat16):
            field(points, dirs, pose)
        casts = sum(e.count for e in prof.key_averages() if e.key == "aten::_to_copy")
        return out, grads, casts

    once, once_grads, once_casts = run()
    monkeypatch.setattr(sparse_parts, "matmul_dtype", lambda reference: reference.dtype)  # autocast casts per part
    per_part, per_part_grads, per_part_casts = run()
    assert torch.equal(once.sigma, per_part.sigma) and torch.equal(once.rgb, per_part.rgb)
    assert len(once_grads) == len(per_part_grads) > 0
    assert all(torch.equal(a, b) for a, b in zip(once_grads, per_part_grads))
    # each operand cast once instead of once per part: 18 casts fewer per operand, of the density blocks' 2 (inputs,
    # weights) and the selector's 4 more (weights, biases, output weights, its own inputs); NARF_H has no selector
    operands = 2 + (4 if name == "narf_d" else 0)
    assert per_part_casts - once_casts == (19 - 1) * operands


def test_frequency_window_hand_values():
    """BARF's w_k = (1 - cos(pi clamp(alpha - k, 0, 1))) / 2 at alpha = 2.5, L = 4: 1, 1, 1/2, 0 (sin and cos alike)."""
    expected = torch.tensor([1.0, 1.0, 0.5, 0.0] * 2)
    assert torch.allclose(frequency_window(2.5, 4), expected, atol=1e-7)  # float32 cosines of exact angles
    assert torch.equal(frequency_window(3.0, 4), torch.tensor([1.0, 1.0, 1.0, 0.0] * 2))
    encoded = positional_encoding(torch.rand(5, 3), 4)
    assert windowed(encoded, None, 4) is encoded and windowed(encoded, 4.0, 4) is encoded
    kept = windowed(encoded, 1.0, 4).unflatten(-1, (3, 8))  # per scalar [sin k, cos k]: only k = 0 survives
    assert torch.equal(kept[..., [1, 2, 3, 5, 6, 7]], torch.zeros(5, 3, 6))
    assert torch.equal(kept[..., [0, 4]], encoded.unflatten(-1, (3, 8))[..., [0, 4]])


@pytest.mark.parametrize("name", model_names("field", "rigid"))
def test_colour_without_the_view_direction_ignores_it(name):
    """model.view_freqs = 0: the colour is the same from every direction (and the density always was); the default
    (all 4 frequencies) does depend on it."""
    field = _field(name).eval()
    points, dirs = _points()
    pose = _random_pose(n_parts=field.n_parts).select(torch.zeros(4, dtype=torch.long))
    turned = dirs.flip(0)
    assert not torch.allclose(field(points, dirs, pose).rgb, field(points, turned, pose).rgb)
    field.view_freqs = 0
    a, b = field(points, dirs, pose), field(points, turned, pose)
    assert torch.equal(a.sigma, b.sigma) and torch.equal(a.rgb, b.rgb)


@pytest.mark.parametrize("name", ["narf_d", "narf_h", "narf_p", "d_narf"])
def test_fast_path_matches_dense_reference_with_window_and_low_order_directions(name, monkeypatch):
    """The coarse-to-fine window and the kept direction and pose frequencies act alike on the fast paths and the dense
    references (float64: the same sums in another order, as the test above)."""
    monkeypatch.setattr("narf.fields.narf_p.PACKED_SHARE", 1.0)
    fast = _field(name, width=16, dtype=torch.float64)
    dense = _field(name, width=16, dtype=torch.float64)
    dense.load_state_dict(fast.state_dict())
    dense.fast = False
    for model in (fast, dense):
        model.view_freqs, model.pose_freqs, model.point_window = 1, 1, 5.5
    points, dirs = _points(8, 12, seed=5, dtype=torch.float64)
    pose = _random_pose(n_frames=2, dtype=torch.float64).select(torch.tensor([0, 1] * 4))
    a, b = fast(points, dirs, pose), dense(points, dirs, pose)
    if name == "d_narf":  # its fast path skips the head where sigma = 0 (no render weighs that colour)
        inside = (b.part_probs.sum(-1) > 0)[..., None]
        a.rgb, b.rgb = torch.where(inside, a.rgb, 0.0), torch.where(inside, b.rgb, 0.0)
    assert torch.allclose(a.sigma, b.sigma, atol=1e-10) and torch.allclose(a.rgb, b.rgb, atol=1e-10)
    plain = _field(name, width=16, dtype=torch.float64)
    plain.load_state_dict(fast.state_dict())
    assert not torch.allclose(plain(points, dirs, pose).sigma, a.sigma)  # the window does act on the density


@pytest.mark.parametrize("name", ["narf_d", "narf_h", "d_narf"])
def test_jitter_and_pose_dropout_act_in_training_only_and_never_on_the_density(name):
    """model.view_jitter and model.pose_dropout perturb a training forward's colour inputs; evaluation (eval mode)
    is the unperturbed field, to the bit, and the density never changes."""
    field = _field(name)
    points, dirs = _points(64, 6)
    pose = _random_pose(n_frames=2).select(torch.arange(64) % 2)
    reference = field.eval()(points, dirs, pose)
    field.view_jitter, field.pose_dropout = math.radians(10), 0.5
    evaluated = field(points, dirs, pose)
    assert torch.equal(evaluated.sigma, reference.sigma) and torch.equal(evaluated.rgb, reference.rgb)
    torch.manual_seed(3)
    trained = field.train()(points, dirs, pose)
    assert torch.equal(trained.sigma, reference.sigma)
    changed = (trained.rgb - reference.rgb).abs().amax(dim=(1, 2)) > 0
    hit = reference.sigma.amax(dim=1) > 0  # rays with a sample in some box
    assert changed[hit].all()
    field.view_jitter = 0.0  # dropout alone: about half of the rays keep their colour exactly
    torch.manual_seed(4)
    dropped = (field(points, dirs, pose).rgb - reference.rgb).abs().amax(dim=(1, 2)) > 0
    assert 0.2 < dropped[hit].float().mean() < 0.8  # binomial(n >= 40, 1/2): outside [0.2, 0.8] with p < 1e-4


@pytest.mark.parametrize("name", ["narf_d", "narf_h", "narf_p", "d_narf"])
def test_a_colour_without_the_pose_features_is_the_same_in_every_pose(name):
    """model.pose_freqs 0: two poses that differ only in their features xi give the same colour, in training and
    evaluation, to the bit (every pose encodes as gamma(0)); at 4 they differ. At 1 the colour is that of the poses'
    features with the higher frequencies taken at 0, exactly (the same operations: gamma(0) + 1 * (gamma(xi) -
    gamma(0)) per kept frequency, float32 rounding of numbers up to 2 in size). The density never reads xi: equal to
    the bit either way."""
    field = _field(name).eval()
    points, dirs = _points(64, 6)
    pose = _random_pose(n_frames=2).select(torch.arange(64) % 2)
    other = dataclasses.replace(pose, pose_features=pose.pose_features.flip(0))
    a, b = field(points, dirs, pose), field(points, dirs, other)
    hit = a.sigma.amax(dim=1) > 0
    assert torch.equal(a.sigma, b.sigma) and not torch.equal(a.rgb[hit], b.rgb[hit])
    features = pose.pose_features
    field.pose_freqs = 1
    kept = field.encode_pose(features).unflatten(-1, (6, 8))
    full, still = positional_encoding(features / math.pi, 4), positional_encoding(features * 0, 4)
    full, still = full.unflatten(-1, (6, 8)), still.unflatten(-1, (6, 8))
    band = torch.tensor([1, 0, 0, 0] * 2, dtype=torch.bool)  # sin, cos of each frequency (positional_encoding)
    assert torch.allclose(kept[..., band], full[..., band], atol=1e-6)
    assert torch.equal(kept[..., ~band], still[..., ~band])
    field.pose_freqs = 0
    for mode in (field.eval(), field.train()):
        a, b = mode(points, dirs, pose), mode(points, dirs, other)
        assert torch.equal(a.sigma, b.sigma) and torch.equal(a.rgb, b.rgb)


@pytest.mark.parametrize("name", [*model_names("field", "rigid"), "d_narf_dense"])
def test_the_pose_gradient_band_leaves_the_fields_own_gradients_alone(name):
    """With the pose held fixed (no gradient), the band limit of the pose's gradient (pose_gradient_freqs, docs/model.md
    §6) changes no trainable parameter's gradient, for every model: it may act on the pose's path only. D-NARF's
    canonical point also depends on its trained selector, whose gradient must keep every frequency. The other models
    run the same operations in the same order: equal to the bit. D-NARF's band-limited encoding sums the selector's
    gradient over two paths (the passing frequencies through x', the others through x' with the pose detached) where
    the plain one sums it over one: float32 rounding of sums of terms up to 2^9 pi in size, 1e-4 relative; without
    the fix the higher frequencies' share of the selector's gradient is missing, tens of percent."""
    model = name.removesuffix("_dense")
    gradients = []
    for freqs in (None, 4):
        field = _field(model)
        field.fast = name == model
        field.pose_gradient_freqs = freqs
        points, dirs = _points(8, 12, seed=5)
        pose = _random_pose(n_frames=2, n_parts=field.n_parts).select(torch.tensor([0, 1] * 4))
        out = field(points, dirs, pose)
        (out.sigma.sum() + out.rgb.sum()).backward()
        gradients.append({k: p.grad.clone() for k, p in field.named_parameters() if p.grad is not None})
    assert gradients[0].keys() == gradients[1].keys() and gradients[0]
    for key in gradients[0]:
        if model == "d_narf":
            assert torch.allclose(gradients[0][key], gradients[1][key], rtol=1e-4, atol=1e-6), key
        else:
            assert torch.equal(gradients[0][key], gradients[1][key]), key


@pytest.mark.parametrize("name", model_names("field", "rigid"))
def test_the_appearance_code_moves_the_colour_only_and_none_is_the_zero_code(name):
    """model.appearance_dim (docs/model.md §4, *Per-frame appearance*): a frame's code changes its colour, never its
    density (to the bit: the density does not read z_a), and poses without codes (evaluation) are the zero code,
    bit for bit (the same tensor of zeros either way)."""
    field = _field(name, appearance_dim=3).eval()
    points, dirs = _points(4, 16)
    pose = _random_pose(n_parts=field.n_parts).select(torch.zeros(4, dtype=torch.long))
    bare = field(points, dirs, pose)
    zero = field(points, dirs, PoseBatch(**{**pose.__dict__, "appearance": torch.zeros(4, 3)}))
    coded = field(points, dirs, PoseBatch(**{**pose.__dict__, "appearance": torch.full((4, 3), 2.0)}))
    assert torch.equal(bare.rgb, zero.rgb) and torch.equal(bare.sigma, zero.sigma)
    assert torch.equal(coded.sigma, bare.sigma)
    assert (coded.rgb - bare.rgb).abs().amax() > 1e-3  # an O(1) code through an O(1) layer: far above rounding
    with pytest.raises(ValueError, match="appearance"):
        field(points, dirs, PoseBatch(**{**pose.__dict__, "appearance": torch.zeros(4, 5)}))
    with pytest.raises(ValueError, match="not both"):
        _field(name, latent_dim=4, appearance_dim=3)


def test_frames_not_trained_on_borrow_the_pose_features_of_the_trained_frame_standing_nearest():
    """docs/model.md §4, *Colour of frames not trained on*, by hand: bank roots at x = 0, 1, 2 m (frame 3 also at 1 m:
    the tie goes to the lower index); a frame at x = 1.4 takes bank frame 1's xi, one at x = 2.6 frame 2's, a kept
    frame its own; the parts, reach, bones and offsets are the frame's own, exactly."""
    bank, pose = _random_pose(n_frames=4, seed=1), _random_pose(n_frames=3, seed=2)
    for batch, xs in ((bank, [0.0, 1.0, 2.0, 1.0]), (pose, [1.4, 2.6, 1.4])):
        batch.world_from_part[:, 0, :3, 3] = torch.tensor([[x, 0.3, -0.2] for x in xs])
    out = colour_from_nearest_place(pose, bank, torch.tensor([False, False, True]))
    assert torch.equal(out.pose_features[0], bank.pose_features[1])
    assert torch.equal(out.pose_features[1], bank.pose_features[2])
    assert torch.equal(out.pose_features[2], pose.pose_features[2])
    for key in ("world_from_part", "reach", "bone_lengths", "rest_offsets"):
        assert torch.equal(getattr(out, key), getattr(pose, key))
    with pytest.raises(ValueError, match="keep"):
        colour_from_nearest_place(pose, bank, torch.tensor([True]))
