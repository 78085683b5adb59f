"""``make gpu-check`` on the CPU with a tiny budget: every step runs and the figures are written."""

import json

import pytest


@pytest.mark.slow
def test_gpu_check_runs_on_the_cpu(tmp_path, capsys):
    from bench.gpu_check import main

    out = tmp_path / "figures.json"
    argv = ["--minutes", "0.02", "--preset", "tiny", "--frames", "12", "--cameras", "4", "--resolution", "64"]
    assert (
        main([*argv, "--work", str(tmp_path), "--device", "cpu", "--skip-tests", "--limit", "1", "--out", str(out)])
        == 0
    )
    figures = json.loads(out.read_text())
    assert figures["device"] == "cpu" and figures["steps"] > 0 and figures["rays_per_s"] > 0
    assert figures["peak_gpu_memory_gib"] is None and figures["novel_pose_psnr"] > 5
    assert "gpu-check: device cpu" in capsys.readouterr().out
