"""Bad input, narf-experiments compare: malformed tables. Each case: exit code 2, one ``narf-xxx: error:`` line naming
the file or the flag, no traceback, nothing new that looks finished (helpers: tests/bad_input.py)."""

import json
from pathlib import Path

import pytest

from pipelines.cli.common import run_cli


def _table(tmp_path, mutate):

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

    path = _table(tmp_path, mutate)
    capsys.readouterr()
    assert run_cli("narf-experiments", experiments.main, ["compare", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("narf-experiments: error: ") and message in err[0], err
    assert str(path) in err[0]
