"""Bad input, narf-calibrate: missing or empty shot folders, board flags and board files. Each case: exit code 2, one
``narf-xxx: error:`` line naming the file or the flag, no traceback, nothing new that looks finished (helpers:
tests/bad_input.py)."""

import cv2
import numpy as np
import pytest
from bad_input import expect_error, expect_usage_error


def test_calibrate_bad_folders(tmp_path, capsys):
    expect_error(capsys, "narf-calibrate", [tmp_path / "missing"], "missing")
    (tmp_path / "empty").mkdir()
    expect_error(capsys, "narf-calibrate", [tmp_path / "empty"], "calib")
    shots = tmp_path / "cap" / "calib"
    (shots / "Camera_B1").mkdir(parents=True)
    for shot, size in (("000", (64, 48)), ("001", (80, 60))):
        cv2.imwrite(str(shots / "Camera_B1" / f"{shot}.jpg"), np.full((size[1], size[0], 3), 128, np.uint8))
    expect_error(capsys, "narf-calibrate", [tmp_path / "cap"], "are 64x48")
    (shots / "Camera_B1" / "000.jpg").write_text("not a jpeg")
    message = expect_error(capsys, "narf-calibrate", [tmp_path / "cap"], "000.jpg")
    assert not (tmp_path / "cap" / "calibration").exists(), message


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


def test_checkerboard_flags_are_checked_before_the_work(tmp_path, capsys):
    """--compare with no camera in common, and an --out that is a file, are refused before any shot is read."""
    from pipelines.cli import calibrate
    from pipelines.cli.common import run_cli
    from pipelines.datasets.camera import Camera
    from pipelines.datasets.rig_files import write_qualisys

    folder = tmp_path / "shots" / "int_cam01_img"
    folder.mkdir(parents=True)
    cv2.imwrite(str(folder / "a.png"), np.zeros((48, 64), np.uint8))  # would fail to calibrate: never reached
    other = Camera("x9", np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]]), np.zeros(5), np.eye(4), 64, 48)
    write_qualisys(tmp_path / "rig.qca.txt", [other])
    (tmp_path / "file").write_text("x")
    for extra, message in (
        (["--compare", tmp_path / "rig.qca.txt"], "none of its cameras ['x9'] is one of the shots' cameras ['cam01']"),
        (["--out", tmp_path / "file"], "file: exists and is not a folder"),
    ):
        argv = [str(a) for a in [tmp_path / "shots", "--checkerboard", "4x7", *extra]]
        assert run_cli("narf-calibrate", calibrate.main, argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
