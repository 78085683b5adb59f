"""Part grids (narf.grids, docs/model.md §2): the fast lookup against the obvious loop, the hash by hand, trilinear
interpolation against a linear function, and NARF_D with grids against its dense reference."""

import shutil
import subprocess

import pytest
import torch

from narf.fields import build_field
from narf.fields.common import PoseBatch
from narf.grids import (
    GridShape,
    PartGrids,
    grid_features,
    grid_features_reference,
    grid_smoothness,
    level_window,
    random_vertices,
    vertex_rows,
)
from tests.test_fields import _points, _random_pose
from tests.test_rigged import VALIDATE, VALIDATOR

#: two one-to-one levels (9 and 12 vertices an axis fit in 4 bits: 2^12 rows) and three hashed ones (18, 27, 41)
SHAPE = GridShape(levels=5, features=3, min_resolution=8, max_resolution=40, log2_rows=12)


def _table(shape=SHAPE, n_parts=4, dtype=torch.float64, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(shape.levels * n_parts * shape.rows, shape.features, generator=gen, dtype=dtype)


def test_levels_and_which_are_hashed():
    assert SHAPE.resolutions() == [8, 11, 17, 26, 40]  # floor(8 * 5^(l/4)): 8, 11.96, 17.89, 26.75, 40
    assert SHAPE.axis_bits() == [4, 4, 5, 5, 6]
    assert SHAPE.hashed() == [False, False, True, True, True]  # 3 * 5 bits > 12
    assert SHAPE.width == 15


def test_the_hash_by_hand():
    """Instant-NGP's spatial hash, computed with Python's unbounded integers."""
    vertex = torch.tensor([[5, 17, 30], [0, 0, 0], [33, 1, 2]])
    got = vertex_rows(vertex, SHAPE.multipliers()[4], 4096).tolist()
    want = [(x * 1 ^ y * 2654435761 ^ z * 805459861) % 4096 for x, y, z in vertex.tolist()]
    assert got == want
    # one to one at 8 cells: 4 bits an axis
    assert vertex_rows(vertex[:2] % 9, SHAPE.multipliers()[0], 4096).tolist() == [5 + 16 * (8 + 16 * 3), 0]


def test_fast_lookup_matches_the_loop_in_value_and_gradient():
    n_parts = 4
    table = _table(n_parts=n_parts).requires_grad_(True)
    gen = torch.Generator().manual_seed(1)
    u = (torch.rand(500, 3, generator=gen, dtype=torch.float64) * 2.2 - 1.1).requires_grad_(True)  # some outside
    part = torch.randint(0, n_parts, (500,), generator=gen)
    fast, slow = grid_features(table, u, part, SHAPE), grid_features_reference(table, u, part, SHAPE)
    # float64, the same 8 products summed in another order: ~1e-16 relative on values of order 1
    assert torch.allclose(fast, slow, atol=1e-12)
    weights = torch.randn(fast.shape, generator=gen, dtype=torch.float64)
    grads_fast = torch.autograd.grad((fast * weights).sum(), [table, u])
    grads_slow = torch.autograd.grad((slow * weights).sum(), [table, u])
    for a, b in zip(grads_fast, grads_slow):
        assert torch.allclose(a, b, atol=1e-10)  # sums of up to ~100 products of order 1 per row, float64
    assert grads_fast[1][(u.abs() > 1).any(-1)].abs().max() > 0  # clamped on a face, gradient of the other axes


def test_the_pose_gradient_passes_the_coarse_levels_only():
    """With gradient_levels = k, u's gradient is that of the first k levels' features alone (docs/model.md §6), the
    fast path's as the loop's; the values and the tables' gradient do not change."""
    n_parts, k = 4, 2
    table = _table(n_parts=n_parts).requires_grad_(True)
    gen = torch.Generator().manual_seed(3)
    u = (torch.rand(300, 3, generator=gen, dtype=torch.float64) * 2 - 1).requires_grad_(True)
    part = torch.randint(0, n_parts, (300,), generator=gen)
    weights = torch.randn(300, SHAPE.width, generator=gen, dtype=torch.float64)
    full = grid_features(table, u, part, SHAPE)
    limited = grid_features(table, u, part, SHAPE, gradient_levels=k)
    slow = grid_features_reference(table, u, part, SHAPE, gradient_levels=k)
    assert torch.equal(full, limited)
    coarse = k * SHAPE.features
    coarse_only = torch.autograd.grad((full[:, :coarse] * weights[:, :coarse]).sum(), u, retain_graph=True)[0]
    table_full, u_full = torch.autograd.grad((full * weights).sum(), [table, u])
    got_table, got_u = torch.autograd.grad((limited * weights).sum(), [table, u])
    slow_u = torch.autograd.grad((slow * weights).sum(), u)[0]
    # float64 sums of the same products in the same order: exact; against the loop as in the test above
    assert torch.equal(got_u, coarse_only) and torch.equal(got_table, table_full)
    assert torch.allclose(slow_u, got_u, atol=1e-10)
    assert (got_u - u_full).abs().max() > 1e-3  # the fine levels held


def test_trilinear_interpolation_reproduces_a_linear_function():
    """A one-to-one level whose table holds f(v) = a . v + b at every vertex v gives f(x) at any point x in cells."""
    shape = GridShape(levels=1, features=1, min_resolution=6, max_resolution=6, log2_rows=9)
    side = 7
    grid = torch.stack(torch.meshgrid(*[torch.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)  # (x, y, z)
    table = torch.zeros(shape.rows, 1, dtype=torch.float64)
    a, b = torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64), 0.7
    table[vertex_rows(grid, shape.multipliers()[0], shape.rows), 0] = grid.double() @ a + b
    u = torch.rand(200, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2)) * 2 - 1
    x = (u + 1) / 2 * 6
    got = grid_features(table, u, torch.zeros(200, dtype=torch.long), shape)[:, 0]
    assert torch.allclose(got, x @ a + b, atol=1e-12)


def test_level_window_fades_the_finer_levels():
    assert level_window(None, 4) is None and level_window(4.0, 4) is None
    assert level_window(2.0, 4).tolist() == [1.0, 1.0, 0.0, 0.0]
    assert level_window(2.5, 4)[2].item() == pytest.approx(0.5)
    grids = PartGrids(2, SHAPE)
    u, part = torch.zeros(3, 3), torch.tensor([0, 1, 1])
    out = grids(u, part, alpha=1.0).reshape(3, SHAPE.levels, SHAPE.features)
    assert out[:, 1:].abs().max() == 0 and out[:, 0].abs().max() > 0


def test_smoothness_is_zero_on_a_constant_table_and_counts_neighbours():
    n_parts = 3
    vertices, axis = random_vertices(SHAPE, n_parts, 64, torch.Generator().manual_seed(0))
    assert (vertices[..., 1:] < torch.tensor(SHAPE.resolutions())[:, None]).all()
    constant = torch.ones(SHAPE.levels * n_parts * SHAPE.rows, SHAPE.features)
    assert grid_smoothness(constant, SHAPE, vertices, axis).item() == 0
    # one-to-one level 0 (4 bits an axis) holding its vertex's x coordinate: neighbours along x differ by 1, along y
    # and z by 0
    rows = 4096
    table = torch.zeros(n_parts * rows, 3)
    table[:, 0] = (torch.arange(n_parts * rows) % 16).float()
    got = grid_smoothness(table, GridShape(1, 3, 8, 8, 12), vertices[:, :1], axis[:, :1])
    assert got.item() == pytest.approx((axis[:, 0] == 0).double().mean().item())


@pytest.mark.parametrize("shading", [False, True])
def test_narf_d_with_grids_fast_path_matches_dense_reference(shading):
    """As test_fields' fast-path test, NARF_D reading part grids: the in-box pairs' lookups and per-part blocks equal
    the dense model's (R, S, P) lookups with the out-of-box blocks masked; with shading, the blended part rotations
    of the normals too."""
    options = dict(encoding="grid", grid_levels=4, grid_features=2, grid_min_resolution=4, grid_max_resolution=24)
    torch.manual_seed(0)
    fast = build_field("narf_d", width=16, grid_log2_rows=10, shading=shading, **options).double()
    torch.nn.init.normal_(fast.grids.table, std=0.5)  # features of order 1, so that the density reads them
    if shading:  # a lighting that varies with the normal, so that the rotations count
        torch.nn.init.normal_(fast.head.lighting, std=1.0)
    dense = build_field("narf_d", width=16, grid_log2_rows=10, shading=shading, **options).double()
    dense.load_state_dict(fast.state_dict())
    dense.fast = False
    half_extents = torch.linspace(0.05, 0.8, 19, dtype=torch.float64)[:, None].expand(19, 3)
    for field in (fast, dense):
        field.set_boxes(torch.zeros(19, 3, dtype=torch.float64), half_extents)
    points, dirs = _points(8, 12, seed=5, dtype=torch.float64)
    points[0, :3] = 20.0
    pose = _random_pose(n_frames=2, dtype=torch.float64).select(torch.tensor([0, 1] * 4))
    points.requires_grad_(True)
    a, b = fast(points, dirs, pose), dense(points, dirs, pose)
    # float64, per-part matmuls against one wide one (~1e3 operations): ~1e-12
    assert torch.allclose(a.sigma, b.sigma, atol=1e-10) and torch.allclose(a.rgb, b.rgb, atol=1e-10)
    grad_a = torch.autograd.grad(a.sigma.sum() + a.rgb.sum(), [points, *fast.parameters()])
    grad_b = torch.autograd.grad(b.sigma.sum() + b.rgb.sum(), [points, *dense.parameters()])
    for ga, gb in zip(grad_a, grad_b):
        assert torch.allclose(ga, gb, atol=1e-8)  # through gamma_10 of the selector, as test_fields says
    assert grad_a[1].abs().max() > 0  # the tables learn (fast.grids.table is the first parameter)


def test_a_grid_field_passes_the_pose_gradient_through_its_coarse_levels(monkeypatch):
    """The field's wiring of the band limit (docs/model.md §6): pose_gradient_freqs K gives the lookups the
    round(K L / 10) coarsest levels (here 8 levels: K = 4 -> 3, 10 -> 8, unset -> all), and the tables' gradient
    does not change, to the bit (the same operations on the tables' path)."""
    import narf.grids

    seen, lookup = [], narf.grids.grid_features
    monkeypatch.setattr(narf.grids, "grid_features", lambda *a: seen.append(a[4]) or lookup(*a))
    options = dict(encoding="grid", grid_levels=8, grid_features=2, grid_min_resolution=4, grid_max_resolution=32)
    torch.manual_seed(0)
    field = build_field("narf_d", width=16, grid_log2_rows=10, **options).double()
    torch.nn.init.normal_(field.grids.table, std=0.5)
    field.set_boxes(torch.zeros(19, 3, dtype=torch.float64), torch.full((19, 3), 0.5, dtype=torch.float64))
    points, dirs = _points(8, 12, seed=5, dtype=torch.float64)
    base = _random_pose(n_frames=2, dtype=torch.float64).select(torch.tensor([0, 1] * 4))
    table_grads = []
    for freqs in (None, 10, 4):
        field.pose_gradient_freqs = freqs
        turned = base.world_from_part.clone().requires_grad_(True)
        out = field(points, dirs, PoseBatch(**{**base.__dict__, "world_from_part": turned}))
        grads = torch.autograd.grad(out.sigma.sum() + out.rgb.sum(), [field.grids.table, turned])
        assert grads[1].abs().max() > 0  # the pose learns
        table_grads.append(grads[0])
    assert seen == [None, 8, 3]
    assert torch.equal(table_grads[0], table_grads[2])


def test_grid_encoding_is_narf_d_only_and_validated():
    from fitting.config import ConfigError, FitConfig, validate_config

    with pytest.raises(ValueError, match="encoding"):
        build_field("narf_d", encoding="hash")
    config = FitConfig()
    config.model.name, config.model.encoding = "narf_h", "grid"
    with pytest.raises(ConfigError, match="model.encoding: narf_h does not take it"):
        validate_config(config)
    config = FitConfig()
    config.model.encoding, config.model.grid_min_resolution, config.model.grid_max_resolution = "grid", 64, 32
    with pytest.raises(ConfigError, match="grid_max_resolution"):
        validate_config(config)


def test_a_smaller_trunk_drops_two_layers_a_block():
    """model.trunk_blocks (docs/model.md §2): 2 + 2 B trunk layers of H. From the paper's B = 3 to 1, four (H, H)
    layers of weight and bias leave: 4 (16 * 16 + 16) = 1,088 parameters at H = 16; the cost table's extras lose
    3 H a block (two ReLUs and a residual add); the option is NARF_D's alone."""
    from fitting.config import ConfigError, FitConfig, validate_config

    paper, small = build_field("narf_d", width=16), build_field("narf_d", width=16, trunk_blocks=1)
    count = lambda field: sum(p.numel() for p in field.parameters())  # noqa: E731
    assert len(paper.head.trunk.blocks) == 3 and len(small.head.trunk.blocks) == 1
    assert count(paper) - count(small) == 4 * (16 * 16 + 16)
    assert paper.head.trunk.extra_flops() - small.head.trunk.extra_flops() == 2 * 3 * 16
    config = FitConfig()
    config.model.name, config.model.trunk_blocks = "narf_h", 1
    with pytest.raises(ConfigError, match="model.trunk_blocks: narf_h does not take it"):
        validate_config(config)
    with pytest.raises(ValueError, match="trunk blocks"):
        build_field("narf_d", trunk_blocks=-1)


@pytest.fixture(scope="module")
def grid_run(data_root_64, tmp_path_factory):
    """A 3-step tiny NARF_D fit whose parts read grids under a one-block trunk, with shading (plumbing, not quality),
    through narf-fit."""
    from pipelines.cli import fit as cli_fit
    from pipelines.cli.common import run_cli

    run = tmp_path_factory.mktemp("grid_run") / "run"
    sets = [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=3", "model.encoding=grid"]
    sets += ["model.grid_log2_rows=10", "train.grid_smoothness=0.01", "model.trunk_blocks=1", "model.shading=true"]
    args = ["--config", "tiny", "--out", str(run), "--quiet", *(a for s in sets for a in ("--set", s))]
    assert run_cli("narf-fit", cli_fit.main, args) == 0
    return run


def test_a_grid_fit_resumes_and_its_checkpoint_loads_without_code(grid_run, tmp_path):
    """The tables are one more tensor of the state: a resumed fit goes on from them, and the checkpoint is read with
    ``weights_only`` (fitting.checkpoint); the run records its encoding."""
    import shutil

    import yaml

    from fitting.checkpoint import load_checkpoint
    from pipelines.cli import fit as cli_fit
    from pipelines.cli.common import run_cli

    run = tmp_path / "run"
    shutil.copytree(grid_run, run)
    assert yaml.safe_load((run / "config.yaml").read_text())["model"]["encoding"] == "grid"
    before = load_checkpoint(run / "checkpoint.pt")
    assert before["step"] == 3
    assert run_cli("narf-fit", cli_fit.main, ["--out", str(run), "--resume", "--set", "train.steps=5", "--quiet"]) == 0
    after = load_checkpoint(run / "checkpoint.pt")
    key = next(k for k in after["model"] if k.endswith("grids.table"))
    assert after["step"] == 5 and not torch.equal(before["model"][key], after["model"][key])


def test_a_grid_fit_evaluates_exports_and_renders(grid_run, tmp_path, capsys):
    """narf-eval, narf-export-mesh (a mesh and the rigged glTF) and narf-render-video read a grid fit as any other."""
    import json

    import trimesh

    from pipelines.cli import eval as cli_eval
    from pipelines.cli import export_mesh as cli_export
    from pipelines.cli import render_video
    from pipelines.cli.common import run_cli

    evaluate = ["--run", str(grid_run), "--split", "novel_pose", "--limit", "1", "--grids", "0", "--quiet"]
    assert run_cli("narf-eval", cli_eval.main, evaluate) == 0
    header = json.loads((grid_run / "eval" / "metrics.json").read_text())
    assert header["encoding"] == "grid" and header["trunk_blocks"] == 1 and header["shading"] is True
    mesh = ["--run", str(grid_run), "--resolution", "16", "--level", "1e-6", "--quiet", "--frame", "0"]
    assert run_cli("narf-export-mesh", cli_export.main, [*mesh, "--out", str(tmp_path / "f0.ply")]) == 0
    assert len(trimesh.load(tmp_path / "f0.ply", force="mesh").faces) > 0
    assert run_cli("narf-export-mesh", cli_export.main, [*mesh, "--rigged", "--out", str(tmp_path / "a.glb")]) == 0
    assert (tmp_path / "a.glb").stat().st_size > 0
    if shutil.which("node") and VALIDATOR.is_file():  # the Khronos glTF Validator, as tests/test_rigged.py runs it
        done = subprocess.run(["node", "-e", VALIDATE, str(VALIDATOR), str(tmp_path / "a.glb")], capture_output=True)
        findings = json.loads(done.stdout.decode().strip().splitlines()[-1])
        assert findings.get("numErrors") == 0 and findings["numWarnings"] == 0, findings
    video = ["--run", str(grid_run), "--kind", "orbit", "--frames", "2", "--out", str(tmp_path / "o.mp4"), "--quiet"]
    assert run_cli("narf-render-video", render_video.main, video) == 0 and (tmp_path / "o.mp4").stat().st_size > 0


def test_a_run_saved_before_the_grids_loads_with_the_frequency_encoding(tmp_path):
    """A checkpoint whose config has no ``model.encoding``, ``model.trunk_blocks``, ``model.shading`` nor grid keys
    (every run fitted before them) loads as the paper's frequency encoding, trunk and colour, its weights as they
    were."""
    from fitting.checkpoint import save_checkpoint
    from fitting.config import load_config
    from fitting.fitted import load_fitted
    from fitting.model_setup import make_field

    config = load_config("tiny")
    saved = config.to_dict()
    for key in [k for k in saved["model"] if k in ("encoding", "trunk_blocks", "shading") or k.startswith("grid_")]:
        del saved["model"][key]
    for key in [k for k in saved["train"] if k.startswith("grid_")]:
        del saved["train"][key]
    field = make_field(config)
    save_checkpoint(tmp_path, {"config": saved, "step": 3, "model": field.state_dict()})
    fitted = load_fitted(tmp_path)
    assert fitted.config.model.encoding == "frequency" and fitted.field.grids is None
    assert fitted.config.model.trunk_blocks == 3 and len(fitted.field.head.trunk.blocks) == 3
    assert fitted.config.model.shading is False and fitted.field.head.lighting is None
    assert all(torch.equal(v, field.state_dict()[k]) for k, v in fitted.field.state_dict().items())
