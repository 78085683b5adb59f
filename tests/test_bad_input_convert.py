"""Bad input, narf-convert-smpl and narf-prepare-thuman: broken model files and sets. Each case: exit code 2, one
``narf-xxx: error:`` line naming the file or the flag, no traceback, nothing new that looks finished (helpers:
tests/bad_input.py)."""

import pickle

import numpy as np
import pytest
from bad_input import (
    expect_error,
)


def test_convert_smpl_and_prepare_thuman(tmp_path, capsys):
    expect_error(capsys, "narf-convert-smpl", [tmp_path / "missing.pkl", tmp_path / "out.pkl"], "missing.pkl")
    (tmp_path / "short.pkl").write_bytes(pickle.dumps({"v_template": np.zeros((10, 3))})[:30])
    expect_error(capsys, "narf-convert-smpl", [tmp_path / "short.pkl", tmp_path / "out.pkl"], "short.pkl")
    assert not (tmp_path / "out.pkl").exists()
    expect_error(capsys, "narf-prepare-thuman", [tmp_path / "raw", "--out", tmp_path / "o"], "raw")
    (tmp_path / "raw").mkdir()
    expect_error(capsys, "narf-prepare-thuman", [tmp_path / "raw", "--out", tmp_path / "o"], "raw")
    assert not (tmp_path / "o").exists()


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
