"""Bad input, narf-eval, narf-render-video and narf-export-mesh, the commands that read a run: bad or damaged runs,
flags and their ranges, motions, Ctrl-C. Each case: exit code 2, one ``narf-xxx: error:`` line naming the file or
the flag, no traceback, nothing new that looks finished (helpers: tests/bad_input.py)."""

import shutil

import numpy as np
import pytest
import scipy.io
import torch
from bad_input import _cli, _interrupt_after, expect_error, expect_usage_error

from pipelines.cli import eval as cli_eval
from pipelines.cli import render_video
from pipelines.cli.common import run_cli


def test_run_commands_on_bad_runs(tiny_run, tmp_path, capsys):
    for prog, extra in (("narf-eval", []), ("narf-render-video", []), ("narf-export-mesh", ["--frame", "0"])):
        extra = [*extra, "--out", tmp_path / "x.ply"] if prog == "narf-export-mesh" else extra
        expect_error(capsys, prog, ["--run", tmp_path / "missing", *extra], "no such run folder")
        empty = tmp_path / f"empty-{prog}"
        empty.mkdir()
        expect_error(capsys, prog, ["--run", empty, *extra], "no checkpoint")
        truncated = tmp_path / f"truncated-{prog}"
        truncated.mkdir()
        (truncated / "checkpoint.pt").write_bytes((tiny_run / "checkpoint.pt").read_bytes()[:2000])
        expect_error(capsys, prog, ["--run", truncated, *extra], "corrupt or unreadable checkpoint")


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda s: s.update(step="abc"), "'step' must be a whole number >= 0, got 'abc'"),
        (lambda s: s.update(config="cpu"), "'config' must be a mapping, got str"),
        (lambda s: s["model"].update({k: v * float("nan") for k, v in s["model"].items()}), "weights are not finite"),
        (lambda s: s.update(model={"trunk.weight": s["model"][next(iter(s["model"]))][:1]}), "do not fit the narf_d"),
    ],
)
def test_damaged_checkpoint_contents_name_the_file(tiny_run, tmp_path, capsys, mutate, message):

    from fitting.checkpoint import save_checkpoint

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    mutate(state)
    save_checkpoint(run, {k: v for k, v in state.items() if k != "format"})
    line = expect_error(capsys, "narf-eval", ["--run", run, "--limit", "1"], message)
    assert str(run) in line and "weights_only" not in line


def test_eval_failure_keeps_the_previous_report(tiny_run, tmp_path, capsys):
    metrics = tiny_run / "eval" / "metrics.json"
    assert run_cli("narf-eval", cli_eval.main, ["--run", str(tiny_run), "--limit", "1", "--quiet"]) == 0
    before = metrics.read_bytes()
    expect_error(capsys, "narf-eval", ["--run", tiny_run, "--split", "cross_dataset"], "not one of its splits")
    expect_error(
        capsys,
        "narf-eval",
        ["--run", tiny_run, "--limit", "1", "--mesh", "--mesh-resolution", "16", "--mesh-level", "1e12"],
        "never reaches",
    )
    assert metrics.read_bytes() == before


def test_video_and_mesh_bad_arguments(tiny_run, tmp_path, capsys):
    good = tmp_path / "good.mp4"
    assert (
        run_cli(
            "narf-render-video",
            render_video.main,
            ["--run", str(tiny_run), "--frames", "2", "--quiet", "--out", str(good)],
        )
        == 0
    )
    before = good.read_bytes()
    base = ["--run", tiny_run, "--quiet", "--out", good]
    expect_error(capsys, "narf-render-video", [*base, "--camera", "9"], "camera 9 out of range")
    expect_usage_error(capsys, "narf-render-video", [*base, "--frames", "0"], "expected a whole number >= 1, got '0'")
    expect_error(capsys, "narf-render-video", [*base[:-1], tmp_path / "v.avi"], "v.avi: the video is an H.264 MP4")
    assert not (tmp_path / "v.avi").exists()
    (tmp_path / "notes.txt").write_text("hello")
    expect_error(
        capsys, "narf-render-video", [*base, "--kind", "poses", "--motion", tmp_path / "notes.txt"], "not a motion"
    )
    np.savez(tmp_path / "other.npz", weights=np.zeros(3))
    expect_error(
        capsys, "narf-render-video", [*base, "--kind", "poses", "--motion", tmp_path / "other.npz"], "missing keys"
    )
    expect_error(
        capsys, "narf-render-video", [*base, "--kind", "orbit", "--motion", tmp_path / "other.npz"], "--kind poses"
    )
    assert good.read_bytes() == before  # the failed runs did not touch the good video
    expect_error(capsys, "narf-render-video", ["--run", tiny_run, "--out", tmp_path], "is a folder")
    mesh = ["--run", tiny_run, "--quiet"]
    expect_error(
        capsys, "narf-export-mesh", [*mesh, "--frame", "0", "--out", tmp_path / "a.stl"], "unknown mesh format"
    )
    expect_error(
        capsys,
        "narf-export-mesh",
        [*mesh, "--frame", "0", "--frames", "1:2", "--out", tmp_path / "a.ply"],
        "--frames A:B picks frames of a --motion",
    )


@pytest.mark.parametrize(
    "prog, flags, message",
    [
        ("narf-eval", ["--limit", "0"], "argument --limit: expected a whole number >= 1, got '0'"),
        ("narf-eval", ["--limit", "-1"], "argument --limit: expected a whole number >= 1, got '-1'"),
        ("narf-eval", ["--grids", "-2"], "argument --grids: expected a whole number >= 0"),
        ("narf-eval", ["--refine-steps", "-5"], "argument --refine-steps: expected a whole number >= 0"),
        ("narf-eval", ["--mesh-resolution", "2"], "argument --mesh-resolution: expected a whole number >= 8"),
        ("narf-render-video", ["--scale", "nan"], "argument --scale: expected a finite number > 0, got 'nan'"),
        ("narf-render-video", ["--scale", "-1"], "argument --scale: expected a finite number > 0, got '-1'"),
        ("narf-render-video", ["--fps", "0"], "argument --fps: expected a whole number >= 1"),
        ("narf-render-video", ["--camera", "-1"], "argument --camera: expected a whole number >= 0"),
        ("narf-export-mesh", ["--frame", "0", "--out", "m.ply", "--resolution", "0"], "argument --resolution"),
    ],
)
def test_numeric_flags_have_ranges(tiny_run, capsys, prog, flags, message):
    expect_usage_error(capsys, prog, ["--run", tiny_run, *flags], message)


def _amass(tmp_path, **change):
    values = {"poses": np.zeros((4, 156)), "trans": np.zeros((4, 3)), "mocap_framerate": np.array(60.0)}
    values |= change
    np.savez(tmp_path / "m.npz", betas=np.zeros(16), gender=np.array("male"), **values)
    return tmp_path / "m.npz"


def _surreal(tmp_path, pose):
    info = {
        "pose": pose.T,
        "shape": np.zeros((10, 3)),
        "zrot": np.zeros((3, 1)),
        "camLoc": np.array([[7.0], [0.0], [1.0]]),
        "joints2D": np.zeros((2, 24, 3)),
        "joints3D": np.zeros((3, 24, 3)),
        "gender": np.ones((3, 1), np.uint8),
    }
    scipy.io.savemat(str(tmp_path / "c_info.mat"), info)
    return tmp_path / "c_info.mat"


MOTION_CASES = [
    (lambda t: _amass(t, mocap_framerate=np.array([60.0, 30.0])), "'mocap_framerate' has shape (2,)"),
    (lambda t: _amass(t, mocap_framerate=np.array("fast")), "'mocap_framerate' is not numeric"),
    (lambda t: _amass(t, poses=np.full((4, 156), "x")), "'poses' is not numeric"),
    (lambda t: _amass(t, poses=np.full((4, 156), np.nan)), "NaN or infinite values"),
    (lambda t: _amass(t, trans=np.zeros((3, 3))), "'trans' has shape (3, 3)"),
    (lambda t: _amass(t, mocap_framerate=np.array(-5.0)), "a frame rate that is not positive"),
    (lambda t: _surreal(t, np.full((3, 72), np.nan)), "'pose' contains NaN"),
    (lambda t: _surreal(t, np.zeros((3, 70))), "'pose' has shape"),
]


@pytest.mark.parametrize("make, message", MOTION_CASES, ids=[m for _, m in MOTION_CASES])
def test_video_refuses_a_bad_motion(tiny_run, tmp_path, capsys, make, message):
    motion = make(tmp_path)
    out = tmp_path / "v.mp4"
    argv = ["--run", tiny_run, "--kind", "poses", "--motion", motion, "--quiet", "--out", out]
    line = expect_error(capsys, "narf-render-video", argv, message)
    assert str(motion) in line and not out.exists()


@pytest.mark.parametrize("value", ["inf", "nan", "0", "-30", "fast"])
def test_motion_fps_is_a_finite_positive_number(tiny_run, tmp_path, capsys, value):
    argv = ["--run", tiny_run, "--kind", "poses", "--motion", _amass(tmp_path), "--motion-fps", value]
    expect_usage_error(capsys, "narf-render-video", argv, "argument --motion-fps: expected a")


@pytest.mark.slow
def test_ctrl_c_during_video_leaves_no_video(tiny_run, tmp_path):
    out = tmp_path / "orbit.mp4"
    args = [*_cli("render_video"), "--run", str(tiny_run), "--frames", "400", "--out", str(out)]
    done = _interrupt_after(args, lambda err: "video orbit:" in err and ("frame/s" in err or "s/frame" in err))
    assert done.returncode == 130 and "interrupted" in done.stderr and "Traceback" not in done.stderr
    assert not out.exists() and not list(tmp_path.glob("*.mp4"))


def test_video_and_export_flags_of_the_new_outputs_are_checked(tiny_run, tmp_path, capsys):
    from pipelines.cli import export_mesh, render_video
    from pipelines.cli.common import run_cli

    cases = [
        (render_video, ["--kind", "path"], "give --camera-path FILE"),
        (render_video, ["--camera-path", str(tmp_path / "missing.json")], "not readable JSON"),
        (render_video, ["--camera-path", str(tmp_path / "a.json"), "--kind", "orbit"], "cannot be a --kind orbit"),
        (export_mesh, ["--rigged", "--fps", "0", "--out", str(tmp_path / "a.glb")], "--fps must be in (0, 1000]"),
        (export_mesh, ["--frame", "0", "--fps", "30", "--out", str(tmp_path / "a.ply")], "--fps and --motion-fps set"),
        (export_mesh, ["--out", str(tmp_path / "a.ply")], "one of --frame N or --motion FILE is required"),
        (export_mesh, ["--frame", "0", "--out", str(tmp_path)], "is a folder; --out names the mesh file"),
    ]
    for module, args, message in cases:
        name = "narf-render-video" if module is render_video else "narf-export-mesh"
        assert run_cli(name, module.main, ["--run", str(tiny_run), "--quiet", *args]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1
    # a flag's value out of range is a usage error (argparse: the usage line, then the error)
    level = ["--run", str(tiny_run), "--frame", "0", "--level", "-5", "--out", str(tmp_path / "a.ply")]
    with pytest.raises(SystemExit) as stop:
        export_mesh.main(level)
    assert stop.value.code == 2 and "argument --level: expected a finite number > 0" in capsys.readouterr().err
    # a range starting with a minus reaches --frames' own check, not argparse's "expected one argument"
    frames = ["--run", str(tiny_run), "--motion", "m.npz", "--frames", "-5:3", "--out", str(tmp_path / "a.ply")]
    with pytest.raises(SystemExit) as stop:
        export_mesh.main(frames)
    assert stop.value.code == 2 and "argument --frames: expected A:B with 0 <= A < B" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
