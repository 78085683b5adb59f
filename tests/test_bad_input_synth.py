"""Bad input, narf-synth: output folders it did not write, sizes and their ranges. Each case: exit code 2, one ``narf-
xxx: error:`` line naming the file or the flag, no traceback, nothing new that looks finished (helpers:
tests/bad_input.py)."""

import pytest
from bad_input import expect_error, expect_usage_error


def test_synth_refuses_foreign_folders(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    expect_error(capsys, "narf-synth", ["--out", tmp_path / "file", "--frames", "2"], "not a folder")
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    expect_error(capsys, "narf-synth", ["--out", tmp_path / "busy", "--frames", "2"], "not empty")
    assert (tmp_path / "busy" / "notes.txt").read_text() == "mine"


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
