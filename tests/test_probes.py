"""Bad-input probes, second pass: files checked at their readers (captures, motions, SMPL models, boards, tables),
output folders and flags. Each case: exit code 2, one ``narf-xxx: error:`` line naming the file or the flag, no
traceback, nothing new that looks finished (test_bad_input.py has the first pass and its helpers)."""

import json
import pickle

import numpy as np
import pytest
import scipy.io
from test_bad_input import _annots, _fit_args, _save_annots, expect_error, expect_usage_error

from pipelines.cli import prepare_capture

# ---- capture contents (narf-fit) --------------------------------------------------------------------------------


def _reflected_R(root):
    path, annots = _annots(root)
    annots["cams"]["R"][1] = np.diag([1.0, 1.0, -1.0]) @ np.asarray(annots["cams"]["R"][1])
    _save_annots(path, annots)
    return "cams['R'][1] is not a rotation (det -1"


def _jpeg_cut_in_half(root):
    _, annots = _annots(root)
    victim = root / "synthetic" / "taichi" / annots["ims"][1]["ims"][0]
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])
    return f"{victim}: truncated JPEG"


def _mask_png_cut(root):
    _, annots = _annots(root)
    victim = (root / "synthetic" / "taichi" / "mask_cihp" / annots["ims"][2]["ims"][0]).with_suffix(".png")
    victim.write_bytes(victim.read_bytes()[:-20])
    return f"{victim}: truncated PNG"


def _poses_as_text(root):
    victim = root / "synthetic" / "taichi" / "new_params" / "1.npy"
    data = np.load(victim, allow_pickle=True).item()
    data["poses"] = np.array([["a"] * 72])
    np.save(victim, np.array(data, dtype=object), allow_pickle=True)
    return f"{victim}: 'poses' is not numeric"


def _nan_shapes(root):
    victim = root / "synthetic" / "taichi" / "new_params" / "2.npy"
    data = np.load(victim, allow_pickle=True).item()
    data["shapes"] = np.full((1, 10), np.nan)
    np.save(victim, np.array(data, dtype=object), allow_pickle=True)
    return f"{victim}: 'shapes' contains NaN"


def _annots_without_ims(root):
    path, annots = _annots(root)
    del annots["ims"]
    _save_annots(path, annots)
    return "expected keys 'cams' and 'ims'"


def _ims_of_wrong_length(root):
    path, annots = _annots(root)
    annots["ims"][4]["ims"] = annots["ims"][4]["ims"][:2]
    _save_annots(path, annots)
    return "ims[4] lists 2 images but cams has 4 cameras"


def _bad_splits(root):
    (root / "synthetic" / "taichi" / "splits.json").write_text('{"train_frames": [0, 99], "train_views": [0]}')
    return "splits.json: 'train_frames' must be a list of whole numbers in [0, 10)"


CAPTURE_CASES = [
    _reflected_R,
    _jpeg_cut_in_half,
    _mask_png_cut,
    _poses_as_text,
    _nan_shapes,
    _annots_without_ims,
    _ims_of_wrong_length,
    _bad_splits,
]


@pytest.mark.parametrize("damage", CAPTURE_CASES, ids=lambda f: f.__name__.strip("_"))
def test_fit_refuses_a_damaged_capture(capture, tmp_path, capsys, damage):
    message = damage(capture)
    expect_error(capsys, "narf-fit", _fit_args(capture, tmp_path / "run"), message)
    assert not (tmp_path / "run").exists(), "a fit that never started leaves no folder"


def test_empty_capture_folder_says_what_is_missing(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    line = expect_error(capsys, "narf-fit", ["--subject", tmp_path / "empty", "--out", tmp_path / "run"], "annots.npy")
    assert line.count(str(tmp_path / "empty")) == 1, line


# ---- output folders of narf-fit ---------------------------------------------------------------------------------


def test_fit_refuses_a_folder_that_is_not_a_run(capture, tmp_path, capsys):
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.jpg").write_bytes(b"mine")
    expect_error(capsys, "narf-fit", _fit_args(capture, out), "not a run folder (it holds holiday.jpg)")
    assert sorted(p.name for p in out.iterdir()) == ["holiday.jpg"]


# ---- motions (narf-render-video --kind poses --motion) ----------------------------------------------------------


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


# ---- narf-synth sizes -------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--frames", "0"], "argument --frames: expected a whole number in [1, 100000], got '0'"),
        (["--resolution", "0"], "argument --resolution: expected a whole number in [1, 8192], got '0'"),
        (["--resolution", "10000000"], "argument --resolution: expected a whole number in [1, 8192]"),
        (["--cameras", "0"], "argument --cameras: expected a whole number in [1, 256]"),
        (["--seed", "-1"], "argument --seed: expected a whole number >= 0"),
        (["--calib-shots", "-3"], "argument --calib-shots"),
        (["--workers", "0"], "argument --workers"),
        (["--dataset", "rigid", "--train-images", "0"], "argument --train-images"),
        (["--dataset", "thuman", "--people", "0"], "argument --people"),
        (["--dataset", "surreal", "--clips", "many"], "argument --clips"),
    ],
)
def test_synth_sizes_have_ranges(tmp_path, capsys, flags, message):
    expect_usage_error(capsys, "narf-synth", ["--out", tmp_path / "s", *flags], message)
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("dataset", ["thuman", "surreal"])
def test_synth_refuses_a_resolution_its_format_fixes(tmp_path, capsys, dataset):
    argv = ["--dataset", dataset, "--resolution", "64", "--out", tmp_path / "s"]
    expect_error(capsys, "narf-synth", argv, f"--resolution: {dataset} images have their format's fixed size")
    assert not (tmp_path / "s").exists()


# ---- narf-calibrate board ---------------------------------------------------------------------------------------


@pytest.fixture()
def shots(tmp_path):
    folder = tmp_path / "cap" / "calib" / "Camera_B1"
    folder.mkdir(parents=True)
    (folder / "000.jpg").write_bytes(b"")  # never read: the board is checked first
    return tmp_path / "cap"


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--squares-x", "-4"], "argument --squares-x: expected a whole number in [2, 100]"),
        (["--squares-y", "1"], "argument --squares-y"),
        (["--square-length", "nan"], "argument --square-length: expected a finite number > 0"),
        (["--marker-length", "-0.1"], "argument --marker-length"),
    ],
)
def test_calibrate_board_flags_have_ranges(shots, capsys, flags, message):
    expect_usage_error(capsys, "narf-calibrate", [shots, *flags], message)


@pytest.mark.parametrize(
    "text, message",
    [
        ('{"squares_x": "five"}', "board squares_x: expected a whole number of squares in [2, 100], got 'five'"),
        ("[8, 6]", "board.json: expected a JSON object"),
        ('{"squares_x": 8, "colour": "red"}', "board.json: unknown key(s) ['colour']"),
        ('{"square_length": 0.05, "marker_length": 0.09}', "marker_length 0.09 must be smaller"),
        ('{"dictionary": "DICT_NOPE"}', "unknown ArUco dictionary 'DICT_NOPE'"),
        ('{"square_length": 1e400}', "board square_length: expected a side in metres in (0, 10)"),
        ("{squares_x: 8}", "board.json: not a board definition"),
    ],
)
def test_calibrate_refuses_a_bad_board_json(shots, capsys, text, message):
    (shots / "calib" / "board.json").write_text(text)
    line = expect_error(capsys, "narf-calibrate", [shots], message)
    assert "board.json" in line and not (shots / "calibration").exists()


# ---- SMPL model files (narf-convert-smpl) ------------------------------------------------------------------------


SMPL_CASES = [
    (lambda m: {"v_template": np.full_like(m["v_template"], np.nan)}, "'v_template' contains NaN"),
    (lambda m: {"f": np.where(m["f"] == 0, 10_000_000, m["f"])}, "'f' indexes vertex 10000000, outside 0..6889"),
    (lambda m: {"f": m["f"].astype(np.float64)}, "'f' has shape"),
    (lambda m: {"weights": np.full(m["weights"].shape, "w")}, "'weights' is not numeric"),
    (lambda m: {"posedirs": np.full_like(m["posedirs"], np.inf)}, "'posedirs' contains NaN or infinite"),
    (lambda m: {"kintree_table": np.full((2, 24), 99)}, "'kintree_table' has parents outside 0..23"),
]


@pytest.mark.parametrize("change, message", SMPL_CASES, ids=[m for _, m in SMPL_CASES])
def test_convert_smpl_refuses_a_broken_model(tmp_path, capsys, change, message):
    from pipelines.body.locate import standin_path
    from pipelines.body.model import BodyModel

    if not standin_path().is_file():
        BodyModel()
    with open(standin_path(), "rb") as handle:
        model = pickle.load(handle, encoding="latin1")
    model.update(change(model))
    src = tmp_path / "model.pkl"
    src.write_bytes(pickle.dumps(model))
    line = expect_error(capsys, "narf-convert-smpl", [src, tmp_path / "out.pkl"], message)
    assert str(src) in line and not (tmp_path / "out.pkl").exists()


# ---- narf-experiments compare -------------------------------------------------------------------------------------


def _table(tmp_path, mutate):
    from pathlib import Path

    summary = json.loads((Path(__file__).resolve().parents[1] / "docs" / "results" / "table_b.json").read_text())
    mutate(summary)
    path = tmp_path / "table.json"
    path.write_text(json.dumps(summary))
    return path


TABLE_CASES = [
    (lambda s: s["rows"].update(x="row"), "rows['x'] needs a 'label'"),
    (lambda s: next(iter(s["rows"].values()))["metrics"].clear(), "lacks the split"),
    (lambda s: next(iter(next(iter(s["rows"].values()))["metrics"].values())).update(psnr="high"), "'psnr'] is 'high'"),
    (lambda s: next(iter(next(iter(s["rows"].values()))["metrics"].values())).update(ssim=None), "'ssim'] is None"),
    (lambda s: s.update(rows=[]), "not a table written by narf-experiments run"),
    (lambda s: s.update(table="table-z"), "not a table written by narf-experiments run"),
]


@pytest.mark.parametrize("mutate, message", TABLE_CASES, ids=[m for _, m in TABLE_CASES])
def test_compare_refuses_a_malformed_table(tmp_path, capsys, mutate, message):
    from pipelines.cli import experiments
    from pipelines.cli.common import run_cli

    path = _table(tmp_path, mutate)
    capsys.readouterr()
    assert run_cli("narf-experiments", experiments.main, ["compare", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("narf-experiments: error: ") and message in err[0], err
    assert str(path) in err[0]


# ---- narf-prepare-capture flags ------------------------------------------------------------------------------------


@pytest.mark.parametrize("value", ["down", "z", "w-up", "z-up=high", "z-up=inf", "+z"])
def test_prepare_floor_flag(tmp_path, capsys, value):
    capsys.readouterr()
    with pytest.raises(SystemExit) as usage:
        prepare_capture.main([str(tmp_path), "--out", str(tmp_path / "o"), f"--floor={value}"])
    assert usage.value.code == 2 and "argument --floor" in capsys.readouterr().err.splitlines()[-1]
    assert not (tmp_path / "o").exists()
