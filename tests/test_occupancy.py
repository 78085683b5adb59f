"""Empty-space skipping (narf/occupancy.py) against the dense reference and hand-computed ray-ball geometry."""

import math

import pytest
import torch

from narf.fields import PoseBatch, build_field
from narf.fields.base import Field, FieldOutput
from narf.occupancy import (
    OccupancyGrid,
    cell_index,
    field_ray_bounds,
    flat_cell_index,
    grid_density,
    refresh_cells,
)
from narf.rays import image_pixels, ray_box_intersect, rays_from_pixels
from narf.renderer import bind_field, bind_grid_proposal, image_ray_bounds, render_image, render_rays

RADIUS, SIGMA = 0.3, 5.0


class BallField(Field):
    """Density SIGMA inside a ball of RADIUS about part 0's origin, 0 elsewhere; constant colour (0.2, 0.5, 0.8).
    Part 1's box overlaps part 0's and is empty."""

    uses_part_points = True

    def __init__(self):
        super().__init__(n_parts=2)
        self.dummy = torch.nn.Parameter(torch.zeros(()))  # render_image reads the device and dtype of a parameter

    def _forward(self, inputs):
        x_local = inputs.x_local
        sigma = torch.where(x_local[:, :, 0].norm(dim=-1) <= RADIUS, SIGMA, 0.0) + 0 * self.dummy
        rgb = torch.tensor([0.2, 0.5, 0.8]).expand(*sigma.shape, 3)
        return FieldOutput(sigma, rgb, None)


def _identity_pose(n=1, n_parts=2):
    return PoseBatch(
        torch.eye(4).expand(n, n_parts, 4, 4).clone(),
        torch.ones(n),
        torch.zeros(n, 0),
        torch.zeros(n, n_parts, 6),
        torch.zeros(n, n_parts, 3),
    )


def _ball_field(resolution=32):
    field = BallField()
    field.set_boxes(torch.tensor([[0.0, 0.0, 0.0], [0.4, 0.0, 0.0]]), torch.full((2, 3), 0.6))
    field.occupancy = OccupancyGrid(2, resolution, threshold=0.01)
    pose = _identity_pose()

    def density(points, frame):
        return field(points[None], torch.tensor([[0.0, 0.0, 1.0]]), pose.select(torch.tensor([frame]))).sigma[0]

    cells = torch.arange(field.occupancy.density.numel())
    refresh_cells(field.occupancy, density, pose, field.box_centres, field.box_half_extents, cells, torch.Generator())
    return field, pose


def test_untouched_grid_is_the_dense_reference():
    """Cells start occupied: the narrowed bounds are the box bounds, so renders are identical to the dense path."""
    torch.manual_seed(0)
    field = build_field("narf_d", width=16)
    field.set_boxes(torch.randn(19, 3) * 0.3, torch.full((19, 3), 0.25))
    pose = _identity_pose(n_parts=19)
    pose.bone_lengths = torch.rand(1, 19)
    K = torch.tensor([[60.0, 0, 16], [0, 60.0, 16], [0, 0, 1]])
    cam_from_world = torch.eye(4)
    cam_from_world[2, 3] = 3.0
    dense = render_image(field, K, cam_from_world, 32, 32, pose, 8, 8)
    field.occupancy = OccupancyGrid(19, 8)
    with_grid = render_image(field, K, cam_from_world, 32, 32, pose, 8, 8)
    for key in dense:
        assert torch.equal(dense[key], with_grid[key]), key


def test_image_render_matches_the_reference_renderer():
    """render_image's default path (inference renderer, compacted rays) against the reference render_rays, on NARF_D's
    fast path."""
    torch.manual_seed(1)
    field = build_field("narf_d", width=16)
    field.set_boxes(torch.randn(19, 3) * 0.3, torch.full((19, 3), 0.25))
    pose = _identity_pose(n_parts=19)
    pose.bone_lengths = torch.rand(1, 19)
    with torch.no_grad():
        field.head.sigma_out.bias.fill_(30.0)  # opaque boxes: real surfaces for the importance samples
    K = torch.tensor([[60.0, 0, 16], [0, 60.0, 16], [0, 0, 1]])
    cam_from_world = torch.eye(4)
    cam_from_world[2, 3] = 3.0
    reference = render_image(field, K, cam_from_world, 32, 32, pose, 8, 16, reference=True, chunk=100)
    inference = render_image(field, K, cam_from_world, 32, 32, pose, 8, 16, chunk=100)
    # the same samples; float32 matmuls over differently sized batches round differently (~1e-6 relative per layer,
    # a dozen layers), and the importance sampler passes that on to the fine depths (docs/model.md §5)
    for key in ("rgb", "mask", "depth"):
        assert (inference[key] - reference[key]).abs().max() < 1e-4, key
    assert (inference["segmentation"] != reference["segmentation"]).float().mean() < 0.01
    assert (reference["mask"] > 0.99).float().mean() > 0.1


def test_image_bounds_skip_only_rays_that_miss_every_box():
    """image_ray_bounds tests the per-part boxes only for rays that cross the world box around them: the same bounds
    as field_ray_bounds on every ray, with and without an occupancy grid."""
    field, pose = _ball_field()
    K = torch.tensor([[40.0, 0, 24], [0, 40.0, 24], [0, 0, 1]])
    cam_from_world = torch.eye(4)
    cam_from_world[2, 3] = 4.0
    origins, dirs = rays_from_pixels(K, cam_from_world, image_pixels(48, 48))
    per_ray = pose.select(torch.zeros(origins.shape[0], dtype=torch.long))
    for grid in (field.occupancy, None):
        field.occupancy = grid
        expected = field_ray_bounds(field, origins, dirs, per_ray)
        got = image_ray_bounds(field, origins, dirs, pose, chunk=100)
        assert torch.equal(got[2], expected[2]) and 0 < expected[2].float().mean() < 0.5
        # the same per-ray arithmetic in other batches: float32 depths ~4, a few eps32
        assert torch.allclose(got[0], expected[0], atol=1e-5) and torch.allclose(got[1], expected[1], atol=1e-5)


def test_refreshed_grid_brackets_the_ball_and_drops_rays_that_miss_it():
    field, pose = _ball_field()
    occupied = field.occupancy.occupied()
    assert 0 < occupied[0].float().mean() < 0.3  # ball volume / box volume = (4/3) pi 0.3^3 / 1.2^3 = 0.065
    assert not occupied[1].any() or occupied[1].float().mean() < occupied[0].float().mean()
    offsets = torch.tensor([0.0, 0.1, 0.2, 0.29, 0.47, 0.55])
    origins = torch.stack([torch.full_like(offsets, -2.0), offsets, torch.zeros_like(offsets)], dim=-1)
    dirs = torch.tensor([1.0, 0.0, 0.0]).expand_as(origins)
    per_ray = pose.select(torch.zeros(6, dtype=torch.long))
    box_near, box_far, box_hit = ray_box_intersect(
        origins, dirs, per_ray.world_from_part, per_ray.reach, field.box_centres, field.box_half_extents
    )
    near, far, hit = field_ray_bounds(field, origins, dirs, per_ray)
    assert box_hit.all()
    chord = torch.sqrt((RADIUS**2 - offsets[:4] ** 2).clamp_min(0))
    entry, exit_ = 2 - chord, 2 + chord  # hand-computed: the ball is centred 2 units along each ray
    # conservative: the narrowed interval holds the whole chord
    assert hit[:4].all() and (near[:4] <= entry).all() and (far[:4] >= exit_).all()
    # tight: an occupied cell holds a measured point of the ball, and the dilation adds one cell, so occupied space
    # lies within two cell diagonals (1.2/32 sqrt 3 each) of the ball; the bounds add one march step
    # ((far - near) / 64 of the box bounds) to that larger ball's chord
    grown = RADIUS + 2 * 1.2 / 32 * math.sqrt(3)
    outer = torch.sqrt(grown**2 - offsets[:4] ** 2)
    step = (box_far - box_near)[:4] / 64
    assert (near[:4] >= 2 - outer - step).all() and (far[:4] <= 2 + outer + step).all()
    assert (far - near)[0] < 0.5 * (box_far - box_near)[0]
    # rays that pass outside the grown ball are dropped although they cross the boxes
    assert not hit[4:].any()


def test_narrowed_bounds_integrate_closer_to_the_reference():
    """Same sample count, smaller intervals: the quadrature of the ball's opacity is closer to a 4096-sample
    reference (midpoint rule on a step function: error ~ the sample spacing, which the grid shrinks)."""
    field, pose = _ball_field()
    offsets = torch.linspace(0.0, 0.28, 15)
    origins = torch.stack([torch.full_like(offsets, -2.0), offsets, torch.full_like(offsets, 0.013)], dim=-1)
    dirs = torch.tensor([1.0, 0.0, 0.0]).expand_as(origins)
    frames = torch.zeros(15, dtype=torch.long)
    per_ray = pose.select(frames)

    def render(n_coarse, use_grid):
        grid, field.occupancy = field.occupancy, field.occupancy if use_grid else None
        near, far, hit = field_ray_bounds(field, origins, dirs, per_ray)
        field.occupancy = grid
        fn = lambda points, ids: field(points, dirs[ids], per_ray.select(ids))  # noqa: E731
        return render_rays(fn, origins, dirs, near, far, hit, n_coarse, 0, randomized=False).mask

    chord = 2 * torch.sqrt(RADIUS**2 - offsets**2 - 0.013**2)
    exact = 1 - torch.exp(-SIGMA * chord)
    reference = render(4096, False)
    # 4096 midpoints over the 1.2-long box span: spacing 3e-4, opacity error <= SIGMA * spacing * e^0 ~ 1.5e-3
    assert torch.allclose(reference, exact, atol=2e-3)
    dense_error = (render(16, False) - exact).abs().mean()
    grid_error = (render(16, True) - exact).abs().mean()
    assert grid_error < 0.7 * dense_error


def test_grid_update_decays_and_keeps_maxima():
    grid = OccupancyGrid(1, 2, threshold=0.5, decay=0.95)
    every = torch.stack(torch.meshgrid(*[torch.arange(2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    zeros = torch.zeros(8, dtype=torch.long)
    assert grid.occupied().all()  # untouched cells (inf) are occupied
    grid.update(zeros, every, torch.tensor([2.0] + [0.0] * 7))
    assert grid.density[0, 0, 0, 0] == 2.0 and grid.density.sum() == 2.0  # untouched cells take the measurement
    grid.update(zeros[:1], every[:1], torch.tensor([0.1]))
    assert grid.density[0, 0, 0, 0] == pytest.approx(2.0 * 0.95)
    assert grid.occupied().all()  # one occupied cell dilates over the 2^3 grid
    for _ in range(29):
        grid.update(zeros[:1], every[:1], torch.tensor([0.0]))
    # 30 float32 products: relative rounding ~ 30 x 6e-8, so rel=1e-5
    assert grid.density[0, 0, 0, 0] == pytest.approx(2.0 * 0.95**30, rel=1e-5) and 2.0 * 0.95**30 < 0.5
    assert not grid.occupied().any()
    with pytest.raises(ValueError):
        OccupancyGrid(1, 1)


def test_fit_with_occupancy_refreshes_the_grid_and_resumes_exactly(data_root_64, tmp_path):
    from fitting.checkpoint import load_checkpoint
    from fitting.config import load_config
    from fitting.run_folder import prepare_run_dir
    from pipelines.runs.fit import resume_run, start_run

    settings = ["render.occupancy=true", "render.occupancy_every=2", "render.occupancy_rounds=2", "train.steps=12"]

    def fit(out, resume=False):
        config = load_config("tiny", [f"data.data_root={data_root_64}", "data.ratio=1.0", *settings])
        run = prepare_run_dir(out, resume)
        if resume:
            return resume_run(run, torch.device("cpu"), progress=False)
        return start_run(run, torch.device("cpu"), config, progress=False)

    straight = fit(tmp_path / "a")
    straight.fit()
    grid = straight.field.occupancy
    assert torch.isfinite(grid.density).all()  # every cell measured (2 rounds of 2 steps each)
    assert grid.occupied_fraction() > 0  # (a 12-step field still has density nearly everywhere)
    first = fit(tmp_path / "b")
    for _ in range(5):
        first.train_step()
    first.checkpoint()
    resumed = fit(tmp_path / "b", resume=True)
    resumed.fit()
    a, b = load_checkpoint(tmp_path / "a"), load_checkpoint(tmp_path / "b")
    # same tolerance as tests/test_fitting.py::test_resume_equals_uninterrupted (float32 reduction order only)
    for key, value in a["model"].items():
        assert torch.allclose(value, b["model"][key], atol=1e-6), key
    assert "occupancy.density" in a["model"]


@pytest.mark.parametrize(
    "dtype, resolution", [(torch.float32, 4), (torch.float32, 24), (torch.float64, 24), (torch.float32, 100)]
)
def test_flat_cell_index_against_cell_index(dtype, resolution):
    """The flat index of the fast lookups equals the row-major index of cell_index's (part, i, j, k), clamping
    included; at N = 100 (19 N^3 > 2^24) it must switch to float64 to stay exact. Integers: compared exactly."""
    torch.manual_seed(0)
    u = (torch.rand(7, 9, 19, 3) * 2.6 - 1.3).to(dtype)  # some coordinates outside the box: clamped to the edge
    u[0, 0] = 1 - 1e-7  # just inside the last cell
    part = torch.arange(19)
    cell = cell_index(u, resolution)
    expected = ((part * resolution + cell[..., 0]) * resolution + cell[..., 1]) * resolution + cell[..., 2]
    assert torch.equal(flat_cell_index(u, part, resolution, 19), expected)


def test_grid_density_against_a_loop():
    torch.manual_seed(0)
    grid = OccupancyGrid(3, resolution=4)
    grid.density.copy_(torch.rand(3, 4, 4, 4) * 10)
    grid.density[1, 0, 0, 0] = float("inf")  # never measured: reads as the ceiling
    u = torch.rand(5, 6, 3, 3) * 2.6 - 1.3  # some samples outside some or all boxes
    u[0, 0] = -0.9  # part 1's unmeasured corner cell, inside every box
    got = grid_density(grid, u, ceiling=1e4)
    expected = torch.zeros(5, 6)
    for r in range(5):
        for s in range(6):
            for p in range(3):
                if u[r, s, p].abs().max() <= 1:
                    i, j, k = cell_index(u[r, s, p], 4).tolist()
                    expected[r, s] = max(expected[r, s], min(float(grid.density[p, i, j, k]), 1e4))
    assert torch.equal(got, expected)  # a gather and a max: no arithmetic
    assert got[0, 0] == 1e4


def test_grid_proposal_places_the_fine_samples_and_skips_the_coarse_field_pass():
    """The field is evaluated once (the final pass, with gradient), and the importance samples follow the grid, not
    the field: with the front half of the ball's cells emptied after the bounds were taken, the fine samples fall
    behind the ball's middle although the field's own weights lie mostly in front (1 - exp(-5 * 0.3) = 78 %)."""
    field, pose = _ball_field()
    origins = torch.tensor([[-2.0, 0.0, 0.0], [-2.0, 0.1, 0.05]])
    dirs = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    frames = torch.zeros(2, dtype=torch.long)
    near, far, hit = field_ray_bounds(field, origins, dirs, pose.select(frames))
    field.occupancy.density[0, :16] = 0  # part 0's cells with u_x < 0: the front half of the ball
    calls, depths = [], []
    field_fn = bind_field(field, dirs, pose, frames)

    def counting(points, ray_ids):
        calls.append(torch.is_grad_enabled())
        depths.append(points[..., 0] + 2)  # depth along +x from x = -2: the ball's middle at 2
        return field_fn(points, ray_ids)

    n_coarse, n_fine = 4, 32
    generator = torch.Generator().manual_seed(0)
    proposal = bind_grid_proposal(field, pose, frames)
    render_rays(counting, origins, dirs, near, far, hit, n_coarse, n_fine, generator=generator, proposal_fn=proposal)
    assert calls == [True]
    # a fine sample lies in a coarse bin of positive proposal weight: within one bin ((far - near) / n_coarse) in
    # front of the first non-empty cell at u_x = 0, i.e. depth 2
    in_front = depths[-1] < 2 - (far - near)[:, None] / n_coarse
    assert (in_front.sum(dim=-1) <= n_coarse).all()  # only coarse samples there
