"""``make gpu-check`` on the CPU with a tiny budget: every step runs, the figures are written, and its PSNR is the one
``narf-fit`` + ``narf-eval`` give for the same capture, config and seed."""

import json

import pytest


@pytest.mark.slow
def test_gpu_check_runs_on_the_cpu_and_gives_the_fits_figure(tmp_path, capsys):
    """20 steps of the tiny preset (steps, not minutes: the same work on any machine). The novel-pose PSNR equals that
    of the same fit through the commands to the figure's 0.01 dB rounding: the same seed and deterministic CPU
    kernels give the same weights up to float32 summation order, far below 0.01 dB."""
    from bench.gpu_check import main
    from pipelines.cli import eval as cli_eval
    from pipelines.cli import fit as cli_fit

    out = tmp_path / "figures.json"
    argv = ["--minutes", "10", "--preset", "tiny", "--frames", "12", "--cameras", "4", "--resolution", "64"]
    argv += ["--work", str(tmp_path), "--device", "cpu", "--skip-tests", "--limit", "1", "--out", str(out)]
    assert main([*argv, "--set", "train.steps=20"]) == 0
    figures = json.loads(out.read_text())
    assert figures["device"] == "cpu" and figures["steps"] == 20 and figures["rays_per_s"] > 0
    assert figures["peak_gpu_memory_gib"] is None
    assert "gpu-check: device cpu" in capsys.readouterr().out
    capture, reference = tmp_path / "taichi-12x4-64", tmp_path / "reference"
    sets = ["--set", "train.steps=20", "--set", "train.validate_every=0"]
    assert cli_fit.main(["--config", "tiny", "--subject", str(capture), "--out", str(reference), "--quiet", *sets]) == 0
    assert (
        cli_eval.main(["--run", str(reference), "--split", "novel_pose", "--limit", "1", "--quiet", "--grids", "0"])
        == 0
    )
    metrics = json.loads((reference / "eval" / "metrics.json").read_text())["splits"]["novel_pose"]
    assert figures["novel_pose_psnr"] == pytest.approx(metrics["full"]["psnr"], abs=0.006)
