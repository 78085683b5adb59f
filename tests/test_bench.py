"""``python -m bench`` keeps each benchmark's rows as it finishes and ``--reuse`` takes them back only when they were
measured on the same machine (an interrupted 70-minute run loses only the benchmark it was in)."""

import json
import sys
from pathlib import Path

import pytest

from bench import __main__ as bench_main


def test_rows_are_saved_and_reused_only_on_the_same_machine(tmp_path, monkeypatch):
    module = tmp_path / "fake_bench.py"
    source = "CALLS = []\ndef run():\n    CALLS.append(1)\n    return [{'model': 'fake', 'value': len(CALLS)}]\n"
    module.write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(bench_main.BENCHMARKS, "fake", "fake_bench")
    saved = tmp_path / "rows" / "fake.json"

    first = bench_main._rows("fake", saved, reuse=False, machine="cpu A")
    assert first == [{"model": "fake", "value": 1}]
    assert json.loads(saved.read_text())["machine"] == "cpu A"
    assert bench_main._rows("fake", saved, reuse=True, machine="cpu A") == first  # taken back, not measured
    assert sys.modules["fake_bench"].CALLS == [1]
    # another machine's rows are measured again (and replace the saved ones); without --reuse always measured
    assert bench_main._rows("fake", saved, reuse=True, machine="cpu B") == [{"model": "fake", "value": 2}]
    assert bench_main._rows("fake", saved, reuse=False, machine="cpu B") == [{"model": "fake", "value": 3}]
    assert json.loads(saved.read_text())["rows"] == [{"model": "fake", "value": 3}]


def test_unknown_benchmark_is_a_usage_error(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["python -m bench", "synth", "fast"])
    with pytest.raises(SystemExit) as stop:  # before any benchmark runs: "synth" would take two minutes
        bench_main.main()
    assert stop.value.code == 2
    assert "unknown benchmark 'fast'" in capsys.readouterr().err


def test_the_benchmarks_cache_is_passed_down_not_written_to_the_environment(tmp_path, monkeypatch, capsys):
    """Without ``$NARF_CACHE`` the benchmarks keep their runs and rows under ``.cache/bench`` of the working folder:
    the calls inside ``python -m bench`` see it (``cache_dir``), the commands they start get it in their
    environment (``command_environment``), and the process's own environment is left as it was."""
    import os

    module = tmp_path / "cache_bench.py"
    module.write_text(
        "import subprocess, sys\n"
        "from pipelines.datasets.smpl_files import cache_dir, command_environment\n"
        "def run():\n"
        "    code = 'import os; print(os.environ[\"NARF_CACHE\"])'\n"
        "    child = subprocess.run([sys.executable, '-c', code], env=command_environment(), capture_output=True,"
        " text=True, check=True)\n"
        "    return [{'model': 'cache', 'here': str(cache_dir()), 'child': child.stdout.strip()}]\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(bench_main.BENCHMARKS, "cache", "cache_bench")
    monkeypatch.delenv("NARF_CACHE", raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["python -m bench", "cache"])
    bench_main.main()
    expected = str(tmp_path / ".cache" / "bench")
    assert f"| cache | {expected} | {expected} |" in capsys.readouterr().out
    assert (tmp_path / ".cache" / "bench" / "rows" / "cache.json").is_file()
    assert "NARF_CACHE" not in os.environ
    from pipelines.datasets.smpl_files import cache_dir

    assert cache_dir() == Path.home() / ".cache" / "narf-avatar"  # the choice ended with the command


def test_reference_comparison_sees_any_difference():
    """``make reference``'s comparison: nested tensors compared exactly (one ulp, a dtype or a shape differ), JSON
    compared without the keys that name places, machines and times."""
    import torch

    from bench.reference import _equal, _stable

    state = {"model": {"w": torch.ones(3)}, "optimizer": {"state": {0: {"step": torch.tensor(2.0)}}}}
    same = {"model": {"w": torch.ones(3)}, "optimizer": {"state": {0: {"step": torch.tensor(2.0)}}}}
    assert _equal(state, same)
    nudged = torch.nextafter(torch.ones(3), torch.full((3,), 2.0))
    assert not _equal(state, {**same, "model": {"w": nudged}})
    assert not _equal(state, {**same, "model": {"w": torch.ones(3, dtype=torch.float64)}})
    assert not _equal(state, {**same, "model": {"w": torch.ones(1, 3)}})
    a = {"run": "/a", "versions": {"torch": "1"}, "splits": {"x": {"psnr": 20.0, "elapsed_s": 1.0}}}
    b = {"run": "/b", "versions": {"torch": "2"}, "splits": {"x": {"psnr": 20.0, "elapsed_s": 9.0}}}
    assert _stable(a) == _stable(b) and _stable(a) != _stable({**b, "splits": {"x": {"psnr": 20.5}}})


def test_reference_compares_prepared_captures_file_by_file(tmp_path):
    """Two prepared captures: the same when every file is (JSON without its volatile keys); one byte of one image,
    a number of the report, or a file more, and they differ, naming the file."""
    from bench.reference import _compare_captures

    for side, cache in (("a", "/x/.a.detections"), ("b", "/y/.b.detections")):
        (tmp_path / side / "cam01").mkdir(parents=True)
        (tmp_path / side / "cam01" / "000000.jpg").write_bytes(b"\xff\xd8pixels")
        report = {"detections": {"cache": cache, "reused": 3}, "iou": 0.9}
        (tmp_path / side / "report.json").write_text(json.dumps(report))
    a, b = tmp_path / "a", tmp_path / "b"
    assert _compare_captures(a, b) == [("2 files", "same")]
    (b / "cam01" / "000000.jpg").write_bytes(b"\xff\xd8pixelz")
    assert _compare_captures(a, b) == [("2 files", "differs: cam01/000000.jpg")]
    (b / "cam01" / "000000.jpg").write_bytes(b"\xff\xd8pixels")
    (b / "report.json").write_text(json.dumps({"detections": {"cache": "/y", "reused": 3}, "iou": 0.91}))
    assert _compare_captures(a, b) == [("2 files", "differs: report.json")]
    (b / "extra.npy").write_bytes(b"")
    assert _compare_captures(a, b)[0][1].startswith("differ: ['extra.npy']")


def test_docs_overlay_puts_every_camera_side_by_side(tmp_path):
    """``python -m bench.docs_images overlay``: one frame of each camera's overlay, scaled to the picture's height,
    in the cameras' order; a capture without overlays is refused naming it."""
    import cv2
    import numpy as np

    from bench.docs_images import OVERLAY_HEIGHT, overlay_row

    for name, (width, value) in {"cam01": (90, 40), "cam02": (120, 200)}.items():
        (tmp_path / "cap" / "overlay" / name).mkdir(parents=True)
        cv2.imwrite(str(tmp_path / "cap" / "overlay" / name / "000050.jpg"), np.full((160, width, 3), value, np.uint8))
    overlay_row(tmp_path / "cap", tmp_path / "out.jpg", 50)
    picture = cv2.imread(str(tmp_path / "out.jpg"))
    assert picture.shape == (OVERLAY_HEIGHT, 270 + 360, 3)  # 90 and 120 columns scaled by 480 / 160
    assert abs(int(picture[:, :200].mean()) - 40) <= 2 and abs(int(picture[:, 400:].mean()) - 200) <= 2  # JPEG
    with pytest.raises(SystemExit, match="no overlay"):
        overlay_row(tmp_path, tmp_path / "none.jpg", 50)


def test_reuse_reaches_a_benchmark_that_keeps_its_configurations(tmp_path, monkeypatch):
    """``--reuse`` is passed to a benchmark that keeps each finished configuration (``KEEPS_CONFIGURATIONS``) as an
    argument, and the others are called as before."""
    module = tmp_path / "kept_bench.py"
    module.write_text(
        "KEEPS_CONFIGURATIONS = True\ndef run(reuse=False):\n    return [{'model': 'kept', 'reuse': reuse}]\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(bench_main.BENCHMARKS, "kept", "kept_bench")
    assert bench_main._rows("kept", tmp_path / "a.json", reuse=True, machine="m") == [{"model": "kept", "reuse": True}]
    assert bench_main._rows("kept", tmp_path / "b.json", reuse=False, machine="m")[0]["reuse"] is False


def test_step_cost_counts_fewer_operators_with_one_render(data_root_64, capsys, monkeypatch):
    """bench.step_cost: a row per variant; the symmetric step's sets rendered by a call each (render=alone) run more
    operators than in one call (each call runs the field's per-part loops again); ``draw=exact`` draws every step's
    pixels with the reference draw and no other variant does; a folder that is not a prepared capture is a usage
    error naming it."""
    import fitting.data
    from bench import step_cost

    exact_draws, reference = [], fitting.data.pool_pixels_exact
    monkeypatch.setattr(fitting.data, "pool_pixels_exact", lambda *a: exact_draws.append(1) or reference(*a))
    capture = data_root_64 / "synthetic" / "taichi"
    mirror = "train.mirror_weight=0.1,train.mirror_rays=32"
    argv = ["--subject", str(capture), "--preset", "tiny", "--steps", "2", "--warmup", "1"]
    assert step_cost.main([*argv, f"one={mirror}", f"alone={mirror},render=alone"]) == 0
    fallbacks = len(exact_draws)  # views whose smallest pool got too few of the fast draw's hits
    assert fallbacks < 48 / 4, "48 views drawn (2 variants x 6 steps x 4 images), most by the fast draw"
    rows = [
        line.split("|")
        for line in capsys.readouterr().out.splitlines()
        if line.startswith("| one") or line.startswith("| alone")
    ]
    operators = {row[1].strip(): int(row[4].replace(",", "")) for row in rows}
    assert operators["alone"] > 1.5 * operators["one"], operators
    assert step_cost.main([*argv, "exact=draw=exact"]) == 0
    assert "| exact |" in capsys.readouterr().out and len(exact_draws) - fallbacks == 6 * 4  # every view
    assert step_cost.main(["--subject", str(data_root_64)]) == 2
    assert str(data_root_64) in capsys.readouterr().err


def test_the_detail_benchmark_reads_a_run_folder(tmp_path):
    """bench detail's row of a fitted and evaluated run: steps, the median step's milliseconds from the log's rays a
    second and the preset's rays a step, and each split's NB crop and person PSNR."""
    import json

    import yaml

    from bench.bench_detail import SPLITS, measured

    (tmp_path / "eval").mkdir()
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({"train": {"images_per_step": 16, "rays_per_image": 32}}))
    rows = [{"step": 50, "rays_per_s": 5120.0}, {"step": 100, "rays_per_s": 4096.0}, {"step": 120, "rays_per_s": 1.0}]
    (tmp_path / "log.jsonl").write_text("\n".join(json.dumps(r) for r in rows))
    splits = {s: {"nb_crop": {"psnr": 22.0 + i, "breakdown": {"psnr_person": 20.0 + i}}} for i, s in enumerate(SPLITS)}
    (tmp_path / "eval" / "metrics.json").write_text(json.dumps({"splits": splits}))
    row = measured({"capture": "real"}, tmp_path)
    assert row["steps"] == 120 and row["ms / step"] == 125.0  # 512 rays at the median 4,096 rays a second
    assert row["novel_view NB crop"] == 23.0 and row["novel_pose person"] == 22.0
