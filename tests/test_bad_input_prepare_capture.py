"""Bad input, narf-prepare-capture: flags (the recordings' own bad-input cases need the synthetic recording of
test_prepare_capture.py and stay there). Each case: exit code 2, one ``narf-xxx: error:`` line naming the file or
the flag, no traceback, nothing new that looks finished (helpers: tests/bad_input.py)."""

import pytest

from pipelines.cli import prepare_capture


@pytest.mark.parametrize("value", ["down", "z", "w-up", "z-up=high", "z-up=inf", "+z"])
def test_prepare_floor_flag(tmp_path, capsys, value):
    capsys.readouterr()
    with pytest.raises(SystemExit) as usage:
        prepare_capture.main([str(tmp_path), "--out", str(tmp_path / "o"), f"--floor={value}"])
    assert usage.value.code == 2 and "argument --floor" in capsys.readouterr().err.splitlines()[-1]
    assert not (tmp_path / "o").exists()
