"""Bad input, narf-fit: damaged captures (at the loader and at the readers), flags, output folders that are not runs or
cannot be written, Ctrl-C. Each case: exit code 2, one ``narf-xxx: error:`` line naming the file or the flag, no
traceback, nothing new that looks finished (helpers: tests/bad_input.py)."""

import errno
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from bad_input import (
    _annots,
    _cli,
    _fit_args,
    _interrupt_after,
    _save_annots,
    expect_error,
)


def _nan_K(root):
    path, annots = _annots(root)
    annots["cams"]["K"][1] = np.full((3, 3), np.nan)
    _save_annots(path, annots)
    return "cams['K'][1] contains NaN"


def _singular_K(root):
    path, annots = _annots(root)
    annots["cams"]["K"][2] = np.zeros((3, 3))
    _save_annots(path, annots)
    return "cams['K'][2] is singular"


def _degenerate_R(root):
    path, annots = _annots(root)
    annots["cams"]["R"][0] = np.zeros((3, 3))
    _save_annots(path, annots)
    return "cams['R'][0] is not a rotation"


def _missing_frame_in_one_camera(root):
    path, annots = _annots(root)
    victim = root / "synthetic" / "taichi" / annots["ims"][0]["ims"][1]
    victim.unlink()
    return f"{victim}: missing or unreadable image"


def _truncated_image(root):
    path, annots = _annots(root)
    victim = root / "synthetic" / "taichi" / annots["ims"][3]["ims"][0]
    victim.write_bytes(victim.read_bytes()[:40])
    return f"{victim}: truncated JPEG"


def _text_as_image(root):
    path, annots = _annots(root)
    victim = root / "synthetic" / "taichi" / annots["ims"][2]["ims"][0]  # camera 0 trains
    victim.write_text("not an image")
    return f"{victim}: missing or unreadable image"


def _camera_without_images(root):
    path, annots = _annots(root)
    folder = root / "synthetic" / "taichi" / Path(annots["ims"][0]["ims"][3]).parent
    for image in folder.iterdir():
        image.unlink()
    return "missing or unreadable image (camera 3"


def _mixed_sizes(root):
    path, annots = _annots(root)
    victim = root / "synthetic" / "taichi" / annots["ims"][5]["ims"][0]
    cv2.imwrite(str(victim), np.zeros((32, 48, 3), np.uint8))
    return "image is 48x32"


def _params_wrong_shape(root):
    victim = root / "synthetic" / "taichi" / "new_params" / "0.npy"
    data = np.load(victim, allow_pickle=True).item()
    data["poses"] = np.zeros((1, 69))
    np.save(victim, np.array(data, dtype=object), allow_pickle=True)
    return "'poses' has shape (1, 69)"


def _annots_not_a_dict(root):
    path, _ = _annots(root)
    np.save(path, np.zeros(3))
    return "expected keys 'cams' and 'ims'"


def _annots_truncated(root):
    path, _ = _annots(root)
    path.write_bytes(path.read_bytes()[:100])
    return "annots.npy: unreadable"


def _camera_folder_missing(root):
    path, annots = _annots(root)
    shutil.rmtree(root / "synthetic" / "taichi" / Path(annots["ims"][0]["ims"][2]).parent)
    return "camera folder listed in annots.npy is missing"


CAPTURE_CASES = [
    _nan_K,
    _singular_K,
    _degenerate_R,
    _missing_frame_in_one_camera,
    _truncated_image,
    _text_as_image,
    _camera_without_images,
    _mixed_sizes,
    _params_wrong_shape,
    _annots_not_a_dict,
    _annots_truncated,
    _camera_folder_missing,
]


@pytest.mark.parametrize("damage", CAPTURE_CASES, ids=lambda f: f.__name__.strip("_"))
def test_fit_on_a_broken_capture(capture, tmp_path, capsys, damage):
    message = damage(capture)
    expect_error(capsys, "narf-fit", _fit_args(capture, tmp_path / "run"), message)
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


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


READER_CASES = [
    _reflected_R,
    _jpeg_cut_in_half,
    _mask_png_cut,
    _poses_as_text,
    _nan_shapes,
    _annots_without_ims,
    _ims_of_wrong_length,
    _bad_splits,
]


@pytest.mark.parametrize("damage", READER_CASES, ids=lambda f: f.__name__.strip("_"))
def test_fit_refuses_a_damaged_capture(capture, tmp_path, capsys, damage):
    message = damage(capture)
    expect_error(capsys, "narf-fit", _fit_args(capture, tmp_path / "run"), message)
    assert not (tmp_path / "run").exists(), "a fit that never started leaves no folder"


def test_empty_capture_folder_says_what_is_missing(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    line = expect_error(capsys, "narf-fit", ["--subject", tmp_path / "empty", "--out", tmp_path / "run"], "annots.npy")
    assert line.count(str(tmp_path / "empty")) == 1, line


def test_fit_arguments(capture, tmp_path, capsys):
    out = tmp_path / "run"
    expect_error(capsys, "narf-fit", ["--data-root", tmp_path / "nowhere", "--out", out], "no such data root folder")
    empty = tmp_path / "empty"
    empty.mkdir()
    expect_error(capsys, "narf-fit", ["--subject", "kick", "--data-root", empty, "--out", out], "no subject 'kick'")
    expect_error(capsys, "narf-fit", [*_fit_args(capture, out), "--set", "train.steps=many"], "expected a number")
    expect_error(capsys, "narf-fit", [*_fit_args(capture, out), "--set", "train.nope=1"], "unknown config key")
    expect_error(capsys, "narf-fit", [*_fit_args(capture, out), "--set", "train.steps"], "key=value")
    expect_error(capsys, "narf-fit", ["--out", tmp_path / "none", "--resume"], "no checkpoint to resume")


def test_fit_refuses_a_folder_that_is_not_a_run(capture, tmp_path, capsys):
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.jpg").write_bytes(b"mine")
    expect_error(capsys, "narf-fit", _fit_args(capture, out), "not a run folder (it holds holiday.jpg)")
    assert sorted(p.name for p in out.iterdir()) == ["holiday.jpg"]


def test_unwritable_or_full_output(capture, tmp_path, capsys, monkeypatch):
    import pipelines.cli.fit as fit_module
    from fitting import files, trainer

    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "ro" / "config.yaml"))

    monkeypatch.setattr(files.tempfile, "mkstemp", refuse)  # a read-only folder (root ignores chmod)
    expect_error(capsys, "narf-fit", _fit_args(capture, tmp_path / "ro"), "config.yaml: Permission denied")
    monkeypatch.undo()

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "run" / "checkpoint.pt"))

    monkeypatch.setattr(fit_module, "sys", sys)  # keep the module's own import untouched
    monkeypatch.setattr(trainer, "save_checkpoint", full)
    expect_error(capsys, "narf-fit", _fit_args(capture, tmp_path / "run"), "checkpoint.pt: No space left on device")


@pytest.mark.slow
def test_ctrl_c_during_fit_saves_a_checkpoint(capture, tmp_path):
    from fitting.checkpoint import load_checkpoint

    out = tmp_path / "run"
    args = [*_cli("fit"), *map(str, _fit_args(capture, out)), "--set", "train.steps=100000", "--quiet"]
    log = out / "log.jsonl"
    done = _interrupt_after(args, lambda _: log.is_file() and log.read_text().count("\n") >= 2)
    assert done.returncode == 130 and "checkpoint saved" in done.stderr and "Traceback" not in done.stderr
    state = load_checkpoint(out)
    assert state["step"] >= 2
