"""narf-experiments: table definitions, the supplement's orderings, resumable rows, and compare."""

import json
from dataclasses import replace

import pytest

from fitting.checkpoint import save_checkpoint
from pipelines.cli import experiments
from pipelines.cli.common import run_cli
from pipelines.experiments.orderings import check_orderings, paper_results
from pipelines.experiments.runner import Settings, fit_request, run_table
from pipelines.experiments.tables import TABLE_A, TABLE_B, TABLE_C, TABLES
from pipelines.runs.fit import fit
from pipelines.synthetic.rigid import RigidSynthConfig, generate_rigid


@pytest.mark.parametrize("name", sorted(TABLES))
def test_every_ordering_holds_on_the_supplements_numbers(name):
    """The checks encode the supplement's claims: on its own tables each one holds."""
    results = check_orderings(name, paper_results(TABLES[name]))
    assert results and all(r["holds"] is True for r in results), results


def test_orderings_notice_a_reversal():
    paper = paper_results(TABLE_B)
    paper["rt_nerf"]["test"]["mask_l2"] = 40.0  # now worse than RT-NeRF w/o xi (29.2)
    verdicts = {r["claim"]: r["holds"] for r in check_orderings("table-b", paper)}
    assert verdicts == {"RT-NeRF > RT-NeRF w/o xi (Mask L2) > RP-NeRF": False, "RP-NeRF fails": True}
    assert check_orderings("table-b", {})[0]["holds"] is None


def test_resume_gets_the_rest_of_the_budget(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    save_checkpoint(run_dir, {"elapsed": 120.0, "step": 7, "config": {}, "model": {}})
    request = fit_request(TABLE_B, TABLE_B.rows[0], Settings(budget_minutes=5.0), run_dir)
    assert request.resume and request.max_minutes == 3.0  # 5 min - 120 s (exact in binary: 5 - 2)


def test_cnn_rows_take_the_cnn_presets(tmp_path):
    presets = {}
    for table, preset in ((TABLE_A, "cpu"), (TABLE_A, "paper"), (TABLE_C, "cpu")):
        row = {r.name: r for r in table.rows}["cnn"]
        presets[table.name, preset] = fit_request(table, row, Settings(preset=preset), tmp_path / "run").preset
    assert presets == {("table-a", "cpu"): "ae_cnn", ("table-a", "paper"): "ae_cnn_paper", ("table-c", "cpu"): "cnn"}


def test_rows_resume_and_compare(tmp_path, capsys):
    data = generate_rigid(tmp_path / "rigid", RigidSynthConfig(4, 1, 32), progress=False)
    calls = []

    def tiny_fit(table, row, settings, run_dir):
        """The real fit at the tiny preset; the second row is interrupted once, as by Ctrl-C."""
        calls.append(row.name)
        if row.name == "rt_nerf_no_pose" and calls.count(row.name) == 1:
            raise KeyboardInterrupt
        request = fit_request(table, row, settings, run_dir)
        fit(replace(request, preset="rigid_tiny", max_minutes=None) if not request.resume else request)

    settings = Settings(budget_minutes=1.0, limit=1, data_root=str(data), device="cpu")
    with pytest.raises(KeyboardInterrupt):
        run_table(TABLE_B, tmp_path / "out", settings, progress=lambda _: None, fitter=tiny_fit)
    assert (tmp_path / "out" / "table-b" / "rp_nerf" / "result.json").is_file()
    assert not (tmp_path / "out" / "table-b" / "table.json").exists()
    summary = run_table(TABLE_B, tmp_path / "out", settings, progress=lambda _: None, fitter=tiny_fit)
    assert calls == ["rp_nerf", "rt_nerf_no_pose", "rt_nerf_no_pose", "rt_nerf"]  # the finished row is not refit
    row = summary["rows"]["rt_nerf"]
    assert (
        row["cost"]["steps"] == 30
        and row["cost"]["params"] > 0
        and set(row["metrics"]["test"])
        == {
            "mask_l2",
            "psnr",
            "ssim",
        }
    )
    saved = json.loads((tmp_path / "out" / "table-b" / "table.json").read_text())
    assert [o["claim"] for o in saved["orderings"]] == [o["claim"] for o in summary["orderings"]]
    capsys.readouterr()
    assert run_cli("narf-experiments", experiments.main, ["compare", str(tmp_path / "out" / "table-b")]) == 0
    out = capsys.readouterr().out
    assert "| RT-NeRF | test |" in out and "16.9/20.05/0.8388" in out  # ours beside the supplement's cell
    (tmp_path / "bad.json").write_text("{}")
    assert run_cli("narf-experiments", experiments.main, ["compare", str(tmp_path / "bad.json")]) == 2
    assert "not a table written by narf-experiments run" in capsys.readouterr().err
    with pytest.raises(ValueError, match="budget_minutes=1.0"):  # one table, one budget
        run_table(TABLE_B, tmp_path / "out", Settings(budget_minutes=2.0, limit=1, data_root=str(data)))
    assert run_cli("narf-experiments", experiments.main, ["run", "table-b", "--rows", "nerf"]) == 2
    assert "table-b has no row nerf" in capsys.readouterr().err
