import shutil
import sys

import pytest
import spawn

from pipelines.cli import synth as cli_synth
from pipelines.cli.common import run_cli
from pipelines.datasets.errors import CaptureError
from pipelines.runs.subject.session import resolve_subject


def test_real_data_wins_over_synthetic(tiny_capture, tmp_path, capsys):
    shutil.copytree(tiny_capture, tmp_path / "zju_mocap" / "CoreView_315", ignore=shutil.ignore_patterns("calib"))
    assert resolve_subject("taichi", tmp_path) == tmp_path / "zju_mocap" / "CoreView_315"
    assert resolve_subject("CoreView_315", tmp_path) == tmp_path / "zju_mocap" / "CoreView_315"
    assert capsys.readouterr().err == ""


def test_falls_back_to_synthetic_with_one_line(tiny_capture, tmp_path, capsys):
    shutil.copytree(tiny_capture, tmp_path / "synthetic" / "taichi")
    assert resolve_subject("taichi", tmp_path) == tmp_path / "synthetic" / "taichi"
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "synthetic stand-in" in err[0]


def test_unknown_subject_and_bad_root(tmp_path):
    with pytest.raises(CaptureError, match="no subject 'kick'"):
        resolve_subject("kick", tmp_path)
    (tmp_path / "file").write_text("")
    with pytest.raises(CaptureError, match="data root is a file"):
        resolve_subject("taichi", tmp_path / "file")
    with pytest.raises(CaptureError, match="not generated yet"):
        resolve_subject("taichi", tmp_path / "empty", generate=False, quiet=True)


def test_synth_cli_errors_are_one_line(tmp_path, capsys):
    code = run_cli("narf-synth", cli_synth.main, ["--out", str(tmp_path / "o"), "--resolution", "8"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("narf-synth: error: resolution >= 32") and "Traceback" not in err
    (tmp_path / "f").write_text("x")
    assert run_cli("narf-synth", cli_synth.main, ["--out", str(tmp_path / "f")]) == 2
    assert "not a folder" in capsys.readouterr().err


def test_synth_cli_writes_a_capture(tmp_path):
    out = tmp_path / "cap"
    result = spawn.run(
        [
            sys.executable,
            "-c",
            "from pipelines.cli.synth import entrypoint; entrypoint()",
            "--out",
            str(out),
            "--resolution",
            "48",
            "--frames",
            "2",
            "--cameras",
            "2",
            "--calib-shots",
            "1",
            "--calib-close-ups",
            "1",
            "--workers",
            "1",
        ],
        120,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr
    assert "wrote" in result.stdout and (out / "annots.npy").is_file() and (out / "calib" / "board.json").is_file()
    assert (out / "calib" / "Camera_B2" / "intrinsics" / "000.jpg").is_file()
    help_text = spawn.run(
        [sys.executable, "-c", "from pipelines.cli.synth import entrypoint; entrypoint()", "--help"],
        60,
        capture_output=True,
        text=True,
    ).stdout
    for flag in ("--subject", "--out", "--resolution", "--frames", "--cameras", "--seed"):
        assert flag in help_text
