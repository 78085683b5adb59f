"""Meshes out: marching cubes over the posed boxes, colours and parts, surface metrics, files, and the CLIs."""

import json

import numpy as np
import pytest
import torch
import trimesh

from fitting.mesh import extract_mesh, surface_metrics, vertex_faces, vertex_normals
from narf.fields.base import Field, FieldOutput
from narf.fields.common import PoseBatch
from pipelines.cli import eval as cli_eval
from pipelines.cli import export_mesh as cli_export
from pipelines.cli.common import run_cli
from pipelines.runs.subject.mesh import write_mesh

RADIUS, RAMP, PEAK = 0.5, 0.01, 200.0


class Ball(Field):
    """One part: density PEAK * sigmoid((RADIUS - |x|) / RAMP) (level PEAK / 2 lies exactly at RADIUS), colour
    (d + 1) / 2 of the viewing direction d; ``hollow``: no density within RADIUS / 2 of the centre (a closed
    pocket)."""

    def __init__(self, hollow: bool = False):
        super().__init__(n_parts=1)
        self.anchor = torch.nn.Parameter(torch.zeros(1))
        self.hollow = hollow

    def _forward(self, inputs):
        points, dirs = inputs.points, inputs.dirs
        sigma = PEAK * torch.sigmoid((RADIUS - points.norm(dim=-1)) / RAMP)
        if self.hollow:
            sigma = torch.where(points.norm(dim=-1) < RADIUS / 2, torch.zeros_like(sigma), sigma)
        rgb = ((dirs[:, None] + 1) / 2).expand(*points.shape[:2], 3)
        return FieldOutput(sigma + 0 * self.anchor, rgb)


def _pose():
    return PoseBatch(
        torch.eye(4)[None, None], torch.ones(1), torch.zeros(1, 0), torch.zeros(1, 1, 6), torch.zeros(1, 1, 3)
    )


def _bumpy_mesh() -> tuple[np.ndarray, np.ndarray]:
    """A jittered icosphere with one degenerate face (three collinear corners) and one vertex no face uses."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(0)
    vertices = sphere.vertices * rng.uniform(0.8, 1.2, (len(sphere.vertices), 1))
    extra = np.array([[2.0, 0, 0], [3.0, 0, 0], [4.0, 0, 0], [9.0, 9, 9]])  # a line, and a lone vertex
    n = len(vertices)
    faces = np.vstack([sphere.faces, [[n, n + 1, n + 2]]])
    return np.vstack([vertices, extra]), faces


def test_vertex_normals_and_faces_match_trimesh():
    vertices, faces = _bumpy_mesh()
    reference = trimesh.Trimesh(vertices, faces, process=False)
    normals = vertex_normals(vertices, faces)
    # float64 sums of at most 6 weighted unit vectors per vertex, in another order than trimesh's sparse product:
    # rounding stays near 1e-15, far below 1e-12
    np.testing.assert_allclose(normals, reference.vertex_normals, atol=1e-12)
    assert np.all(normals[-4:] == 0)  # the degenerate face counts for nothing, the lone vertex has no normal
    around = vertex_faces(len(vertices), faces)
    assert around.shape == reference.vertex_faces.shape
    for mine, theirs in zip(around, reference.vertex_faces):
        assert sorted(mine[mine >= 0]) == sorted(theirs[theirs >= 0])
        assert np.all(np.diff(mine[mine >= 0]) > 0)


def test_marching_cubes_of_an_analytic_ball():
    field = Ball()
    field.set_boxes(torch.zeros(1, 3), torch.full((1, 3), 0.8))
    mesh = extract_mesh(field, _pose(), resolution=48, level=PEAK / 2)
    spacing = 1.6 / 47
    radii = np.linalg.norm(mesh.vertices, axis=1)
    # marching cubes interpolates linearly inside a voxel across the ramp: within half a voxel of the sphere
    assert np.abs(radii - RADIUS).max() < spacing / 2
    assert mesh.faces.shape[1] == 3 and len(mesh.vertices) > 500 and set(np.unique(mesh.parts)) == {0}
    normals = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).face_normals
    assert (np.einsum("fd,fd->f", normals, mesh.vertices[mesh.faces].mean(1)) > 0).all()  # wound outwards
    # colour seen from outside along the normal: d = -x/|x|, rgb = (1 - x/|x|) / 2. Vertex normals average the
    # few triangles around a vertex, whose corners sit up to half a voxel off the sphere: up to ~10 deg of tilt,
    # i.e. sin(10 deg) / 2 = 0.09 in a colour channel, and a few degrees on average (0.03 ~ 3.4 deg); a normal of
    # the wrong sign would be off by |x_i| / |x| ~ 0.5 on average
    error = np.abs(mesh.colours - (1 - mesh.vertices / radii[:, None]) / 2)
    assert error.max() < 0.1 and error.mean() < 0.03
    with pytest.raises(ValueError, match="never reaches the level"):
        extract_mesh(field, _pose(), resolution=16, level=PEAK * 2)


def test_a_closed_pocket_inside_is_no_surface():
    field = Ball(hollow=True)
    field.set_boxes(torch.zeros(1, 3), torch.full((1, 3), 0.8))
    mesh = extract_mesh(field, _pose(), resolution=48, level=PEAK / 2)
    radii = np.linalg.norm(mesh.vertices, axis=1)
    # the outer sphere alone (within half a voxel, as the solid ball's), no vertex near the pocket's wall at R / 2
    assert np.abs(radii - RADIUS).max() < 1.6 / 47 / 2
    assert len(trimesh.Trimesh(mesh.vertices, mesh.faces).split(only_watertight=False)) == 1


def test_surface_metrics_of_concentric_spheres():
    inner = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    outer = trimesh.creation.icosphere(subdivisions=4, radius=1.01)
    metrics = surface_metrics(inner, outer, n_samples=5000)
    # scaled copies: each face of one faces a parallel face 0.01 x (its distance to the centre, 0.999-1) away
    assert metrics["mean_mm"] == pytest.approx(10.0, abs=0.1) and metrics["p95_mm"] == pytest.approx(10.0, abs=0.1)
    assert metrics["normal_consistency"] > 0.999
    shifted = inner.copy()
    shifted.apply_translation([0.02, 0, 0])
    skew = surface_metrics(inner, shifted, n_samples=5000)
    # a 20 mm shift: 20 |cos| on average over the sphere (10 mm), at most 20 mm
    assert 8 < skew["mean_mm"] < 12 and skew["p95_mm"] < 20.5


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb"])
def test_mesh_files_keep_colours_and_parts(tmp_path, suffix):
    from fitting.mesh import ExtractedMesh

    sphere = trimesh.creation.icosphere(subdivisions=2)
    n = len(sphere.vertices)
    mesh = ExtractedMesh(sphere.vertices, sphere.faces, np.tile([1.0, 0.5, 0.0], (n, 1)), np.arange(n) % 19)
    written = write_mesh(tmp_path / f"body{suffix}", mesh)
    back = trimesh.load(tmp_path / f"body{suffix}", process=False, force="mesh")
    np.testing.assert_allclose(back.vertices, sphere.vertices, atol=1e-6)  # float32 in the file
    np.testing.assert_array_equal(back.visual.vertex_colors[0], [255, 128, 0, 255])
    if suffix == ".ply":
        parts = back.metadata["_ply_raw"]["vertex"]["data"]["part"]
    elif suffix == ".glb":
        parts = back.vertex_attributes["_PART"].ravel()
    else:
        assert written[0].name == "body_parts.txt"
        parts = np.loadtxt(written[0], dtype=int)
    np.testing.assert_array_equal(parts, np.arange(n) % 19)
    with pytest.raises(ValueError, match="unknown mesh format"):
        write_mesh(tmp_path / "body.stl", mesh)


def _half_peak(run):
    """Half the peak density of a barely trained run at frame 0 (its level is arbitrary; the plumbing is tested)."""
    from fitting.mesh import density_grid
    from pipelines.runs.subject.mesh import _capture_pose
    from pipelines.runs.subject.session import load_run

    loaded = load_run(run)
    volume, _, _ = density_grid(loaded.field, _capture_pose(loaded, 0, "cpu"), 16)
    return float(volume.max()) / 2


def test_export_mesh_cli_and_eval_mesh(tiny_run, data_root_64, tmp_path, capsys):
    level = f"{_half_peak(tiny_run):.6g}"
    args = ["--run", str(tiny_run), "--resolution", "24", "--level", level, "--quiet"]
    assert run_cli("narf-export-mesh", cli_export.main, [*args, "--frame", "3", "--out", str(tmp_path / "f3.glb")]) == 0
    mesh = trimesh.load(tmp_path / "f3.glb", force="mesh")
    assert len(mesh.faces) > 0 and "_PART" in mesh.vertex_attributes
    capsys.readouterr()
    auto = ["--run", str(tiny_run), "--resolution", "24", "--quiet", "--frame", "3", "--out", str(tmp_path / "a.ply")]
    assert run_cli("narf-export-mesh", cli_export.main, auto) == 0  # no --level: chosen from the training masks
    assert "training views)" in capsys.readouterr().out and (tmp_path / "a.ply").is_file()
    zju = data_root_64 / "synthetic" / "taichi" / "new_params"
    motion = [*args, "--motion", str(zju), "--frames", "2:4", "--out", str(tmp_path / "seq.ply")]
    assert run_cli("narf-export-mesh", cli_export.main, motion) == 0
    assert sorted(p.name for p in tmp_path.glob("seq_*.ply")) == ["seq_00002.ply", "seq_00003.ply"]
    for bad, message in (
        (["--frame", "99", "--out", str(tmp_path / "x.ply")], "frame 99 out of range"),
        (["--frame", "0", "--out", str(tmp_path / "x.stl")], "unknown mesh format"),
        (["--frame", "0", "--level", "1e9", "--out", str(tmp_path / "x.ply")], "never reaches the level"),
    ):
        assert (
            run_cli(
                "narf-export-mesh", cli_export.main, ["--run", str(tiny_run), "--resolution", "16", "--quiet", *bad]
            )
            == 2
        )
        assert message in capsys.readouterr().err
    assert not (tmp_path / "x.ply").exists()
    ev = [
        "--run",
        str(tiny_run),
        "--split",
        "novel_pose",
        "--limit",
        "1",
        "--quiet",
        "--mesh",
        "--mesh-resolution",
        "24",
    ]
    assert run_cli("narf-eval", cli_eval.main, [*ev, "--mesh-level", level]) == 0
    report = json.loads((tiny_run / "eval" / "metrics.json").read_text())
    surface = report["splits"]["novel_pose"]["mesh"]
    assert surface["frames"] == [9] and surface["mean_mm"] > 0 and 0 <= surface["normal_consistency"] <= 1
    assert (tiny_run / "eval" / "meshes" / "novel_pose" / "9.ply").is_file()
    assert "distance to the true surface" in (tiny_run / "eval" / "metrics.md").read_text()


def _ring_cameras(distance: float, focal: float, size: int, count: int = 4) -> list[np.ndarray]:
    """``count`` cameras on a horizontal circle of radius ``distance`` looking at the origin (z up)."""
    cameras = []
    for angle in np.linspace(0, 2 * np.pi, count, endpoint=False):
        centre = distance * np.array([np.cos(angle), np.sin(angle), 0.3])
        forward = -centre / np.linalg.norm(centre)
        right = np.cross(forward, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rotation = np.stack([right, down, forward])
        cam_from_world = np.eye(4)
        cam_from_world[:3, :3], cam_from_world[:3, 3] = rotation, -rotation @ centre
        cameras.append(cam_from_world)
    K = np.array([[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]])
    return [K, *cameras]


def test_max_density_image_against_map_coordinates():
    from scipy.ndimage import map_coordinates

    from fitting.mesh_level import max_density_image
    from narf.rays import image_pixels, rays_from_pixels

    rng = np.random.default_rng(3)
    volume = rng.uniform(0, 10, (12, 15, 18)).astype(np.float32)  # distinct sizes: a swapped axis cannot pass
    origin, spacing = np.array([-0.3, -0.4, -0.5]), 0.05
    K, cam_from_world = _ring_cameras(2.0, 60.0, 24)[:2]
    fast = max_density_image(volume, origin, spacing, K, cam_from_world, (24, 24), stride=3)
    # the oracle: the same samples (entry to exit, every half voxel or closer), interpolated by scipy
    pixels = image_pixels(24, 24).reshape(24, 24, 2)[::3, ::3].reshape(-1, 2).double()
    origins, dirs = (t.numpy() for t in rays_from_pixels(torch.tensor(K), torch.tensor(cam_from_world), pixels))
    high = origin + (np.array(volume.shape) - 1) * spacing
    n = int(np.ceil(np.linalg.norm(high - origin) / (0.5 * spacing))) + 1
    slow = np.zeros(len(origins))
    for r, (o, d) in enumerate(zip(origins, dirs)):
        with np.errstate(divide="ignore"):
            t_a, t_b = (origin - o) / d, (high - o) / d
        t_in, t_out = max(np.minimum(t_a, t_b).max(), 0), np.maximum(t_a, t_b).min()
        if t_out > t_in:
            points = o + np.linspace(t_in, t_out, n)[:, None] * d
            slow[r] = map_coordinates(volume, ((points - origin) / spacing).T, order=1, cval=0.0).max()
    assert (slow > 0).sum() > 20  # most rays cross the grid
    # float32 trilinear weights in grid_sample against float64 in scipy: values up to 10, error ~1e-5
    np.testing.assert_allclose(fast.ravel(), slow, atol=1e-4)


def test_chosen_level_matches_the_masks_silhouette():
    """A soft ball, density PEAK * sigmoid((R - r) / ramp), seen by four cameras whose masks are the true ball of
    radius R: the chosen level's surface lies near R (the level at R is PEAK / 2)."""
    from fitting.mesh_level import LevelView, choose_level
    from narf.rays import image_pixels, rays_from_pixels

    field = Ball()
    field.set_boxes(torch.zeros(1, 3), torch.full((1, 3), 0.8))
    K, *cameras = _ring_cameras(3.0, 600.0, 256)
    views = []
    for cam_from_world in cameras:
        origins, dirs = rays_from_pixels(torch.tensor(K), torch.tensor(cam_from_world), image_pixels(256, 256).double())
        miss = torch.linalg.cross(origins, dirs).norm(dim=1)  # distance of each ray from the centre
        views.append(
            LevelView(K, cam_from_world, (miss < RADIUS).reshape(256, 256).numpy(), np.zeros((256, 256), bool))
        )
    choice = choose_level(field, [(_pose(), views)])
    radius = RADIUS - RAMP * np.log(choice.level / (PEAK - choice.level))  # where the density equals the level
    # candidates are 11 % apart: half a step moves the surface by at most RAMP * 0.11 / (4 * 0.25) ~ 0.06 ramp at the
    # steepest (here 0.6 mm); a 1.6 m grid of 128 samples interpolates the 10 mm ramp over 12.6 mm voxels and the
    # silhouettes are sampled every 2 pixels (10 mm at 3 m): a few mm, pooled over ~2,500 boundary pixels
    assert abs(radius - RADIUS) < 0.005 and choice.iou > 0.97 and choice.n_views == 4
    assert choice.levels.min() < choice.level < choice.levels.max()
