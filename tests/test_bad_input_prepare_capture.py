"""Bad input, narf-prepare-capture: broken recordings (missing folder, two videos of one camera, masks of another
size, unknown calibration, unmatched cameras, bad keypoint files, undecodable video), flags, a floor file, a capture
whose every camera is flagged. Each case: exit code 2, one ``narf-prepare-capture: error:`` line naming the file or
the flag, no traceback, nothing new that looks finished (helpers: tests/bad_input.py)."""

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from bad_input import prepare_error

from pipelines.cli import prepare_capture
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.keypoints import write_openpose
from pipelines.datasets.rig_files import read_qualisys, write_qualisys

FLOORS = ["down", "z", "w-up", "z-up=high", "z-up=inf", "+z"]
PEOPLE = ["first", "near:1,2", "near:1,2,x", "pixel:cam01:5", "pixel:5,6", "near:1,2,nan"]


@pytest.mark.parametrize(("flag", "value"), [("floor", v) for v in FLOORS] + [("person", v) for v in PEOPLE])
def test_prepare_flag_values(tmp_path, capsys, flag, value):
    capsys.readouterr()
    with pytest.raises(SystemExit) as usage:
        prepare_capture.main([str(tmp_path), "--out", str(tmp_path / "o"), f"--{flag}={value}"])
    assert usage.value.code == 2 and f"argument --{flag}" in capsys.readouterr().err.splitlines()[-1]
    assert not (tmp_path / "o").exists()


def test_a_person_pixel_of_an_unknown_camera_is_one_line(recording, tmp_path, capsys):
    rec = recording / "rec"
    flags = ["--keypoints", rec / "keypoints", "--masks", rec / "masks", "--quiet", "--person", "pixel:nocam:5,6"]
    error = prepare_error(capsys, [rec, "--out", tmp_path / "o", *flags])
    assert "nocam is not one of the cameras" in error and not (tmp_path / "o").exists()


def test_a_capture_whose_every_camera_is_flagged_is_refused_unless_kept():
    from pipelines.prepare.request import PrepareRequest
    from pipelines.prepare.run import _refuse_all_flagged

    report = {"cameras": {"a": {}, "b": {}}, "flagged_cameras": {"a": "turned", "b": "turned"}}
    with pytest.raises(CaptureError, match="every camera is flagged .a: turned.; nothing was written"):
        _refuse_all_flagged(report, PrepareRequest(recording=Path("rec"), out=Path("out")))
    _refuse_all_flagged(report, PrepareRequest(recording=Path("rec"), out=Path("out"), keep_flagged=True))
    report["flagged_cameras"].pop("b")
    _refuse_all_flagged(report, PrepareRequest(recording=Path("rec"), out=Path("out")))


def test_bad_recordings_are_one_line(recording, tmp_path, capfd):
    """One line each, at the file descriptor too (ffmpeg's own complaints about a broken video are kept out)."""
    rec = tmp_path / "rec"
    shutil.copytree(recording / "rec", rec)
    out = tmp_path / "out"
    flags = ["--out", out, "--keypoints", rec / "keypoints", "--masks", rec / "masks", "--quiet"]
    assert "no such folder" in prepare_error(capfd, [tmp_path / "missing", *flags])
    shutil.copy(rec / "videos" / "Camera_B1.mp4", rec / "videos" / "Camera_B1.webm")
    assert "camera 'Camera_B1' has several videos (Camera_B1.mp4, Camera_B1.webm)" in prepare_error(
        capfd, [rec, *flags]
    )
    (rec / "videos" / "Camera_B1.webm").unlink()
    mask = next((rec / "masks" / "Camera_B2").iterdir())
    original = mask.read_bytes()
    cv2.imwrite(str(mask), np.zeros((100, 80), np.uint8))
    assert f"{mask}: mask is 80x100, camera 'Camera_B2' records 256x256" in prepare_error(capfd, [rec, *flags])
    mask.write_bytes(original)
    (rec / "calibration" / "rig.txt").write_text("hello")
    assert "unknown calibration format" in prepare_error(
        capfd, [rec, *flags, "--calibration", rec / "calibration" / "rig.txt"]
    )
    other = [c for c in read_qualisys(rec / "calibration" / "Calib.qca.txt")[:3]]
    write_qualisys(
        tmp_path / "three.qca.txt", [type(c)(**{**c.__dict__, "name": f"x{i}"}) for i, c in enumerate(other)]
    )
    assert "match none of the recordings" in prepare_error(
        capfd, [rec, *flags, "--calibration", tmp_path / "three.qca.txt"]
    )
    bad_json = rec / "keypoints" / "Camera_B1_json" / "Camera_B1_000000000003_keypoints.json"
    write_openpose(bad_json, [np.zeros((20, 3))])
    assert "Camera_B1_000000000003_keypoints.json" in prepare_error(capfd, [rec, *flags])
    for path in (rec / "keypoints").rglob("*.json"):
        write_openpose(path, [])
    assert "no person is seen" in prepare_error(capfd, [rec, *flags])
    (rec / "videos" / "Camera_B2.mp4").write_bytes(b"\x00" * 4096)
    assert "Camera_B2.mp4: cannot be decoded" in prepare_error(capfd, [rec, *flags])
    assert not out.exists() and not list(tmp_path.glob(".out*")), "nothing half-written"


def test_a_bad_floor_file_names_itself(tmp_path):
    from pipelines.datasets.floor import read_floor

    for text in (
        '{"up": [0, 0], "height": 0}',
        '{"up": [0, 0, 0], "height": 0}',
        '{"height": 1}',
        "[1, 2",
        '{"up": [0, 0, 1], "height": "NaN"}',
    ):
        (tmp_path / "floor.json").write_text(text)
        with pytest.raises(CaptureError, match="floor.json"):
            read_floor(tmp_path / "floor.json")
