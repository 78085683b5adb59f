"""``make gpu-check``: the project on a GPU in under 8 minutes (docs/guides/speed.md, *On a GPU*).

1. The tests that use CUDA (``tests/test_cuda.py``: a training step against the CPU's, a short fit).
2. A synthetic capture (``narf-synth``'s generator; kept between runs), then a fit of the paper preset for
   ``--minutes`` and ``narf-eval --split novel_pose``.
3. One line and a JSON file (``--out``): the device, steps, rays/s (median of the log), peak GPU memory and the
   novel_pose PSNR.

On a CPU it runs the same steps with whatever budget it is given, as the suite's test does with a tiny one.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m bench.gpu_check", description=__doc__)
    parser.add_argument("--minutes", type=float, default=5.0, help="fit budget")
    parser.add_argument("--preset", default="paper", help="fit preset (configs/)")
    parser.add_argument("--frames", type=int, default=100, help="frames of the synthetic capture")
    parser.add_argument("--cameras", type=int, default=8, help="cameras of the synthetic capture")
    parser.add_argument("--resolution", type=int, default=512, help="image side of the synthetic capture")
    parser.add_argument("--work", type=Path, default=Path("runs/gpu-check"), help="folder of the capture and run")
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    parser.add_argument("--limit", type=int, default=10, help="novel_pose views evaluated")
    parser.add_argument("--skip-tests", action="store_true", help="leave out step 1")
    parser.add_argument("--out", type=Path, default=None, help="JSON of the figures (default: WORK/gpu-check.json)")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a config override of the fit, e.g. --set train.precision=tf32 (repeatable)",
    )
    return parser


def log_rows(run: Path) -> list[dict]:
    """The rows of ``run``'s ``log.jsonl``; none for a fit shorter than ``train.log_every`` steps."""
    log = run / "log.jsonl"
    return [json.loads(line) for line in log.read_text().splitlines()] if log.is_file() else []


def rays_per_s(rows: list[dict], steps: int, trainer, skip: int = 0) -> int:
    """The median rays/s of the log ``rows`` after the first ``skip`` (all of them where no more are left); without
    rows, the fit's mean rate (its ``steps`` over the trainer's elapsed time)."""
    rates = [r["rays_per_s"] for r in rows[skip:]] or [r["rays_per_s"] for r in rows]
    return round(float(np.median(rates)) if rates else steps * trainer.rays_per_step / max(trainer.elapsed, 1e-9))


def peak_gpu_memory_gib(device) -> float | None:
    """GiB that torch allocated on ``device`` at most since the last reset; None off CUDA."""
    import torch

    return round(torch.cuda.max_memory_allocated(device) / 2**30, 2) if device.type == "cuda" else None


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    import torch

    from fitting.config import load_config
    from fitting.files import atomic_write_text
    from fitting.run_folder import auto_device, prepare_run_dir
    from pipelines.cli.eval import main as evaluate
    from pipelines.runs.fit import start_run
    from pipelines.synthetic.capture import is_complete

    device = auto_device(args.device)
    figures = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"}
    if not args.skip_tests:
        started = time.perf_counter()
        tests = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/test_cuda.py"])
        figures.update({"cuda_tests_exit": tests.returncode, "cuda_tests_s": round(time.perf_counter() - started, 1)})
    capture = args.work / f"taichi-{args.frames}x{args.cameras}-{args.resolution}"
    if not is_complete(capture):  # in a process of its own: its render pool forks a process without threads yet
        synth = [str(Path(sys.executable).with_name("narf-synth")), "--out", str(capture)]
        synth += ["--resolution", str(args.resolution), "--frames", str(args.frames), "--cameras", str(args.cameras)]
        synth += ["--calib-shots", "0", "--calib-close-ups", "0", "--workers", str(min(8, os.cpu_count() or 1))]
        subprocess.run(synth, check=True)
    config = load_config(args.preset, [f"data.subject={capture.resolve()}", "train.validate_every=0", *args.set])
    run = prepare_run_dir(args.work / "run", True)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    trainer = start_run(run, device, config, progress=False)
    result = trainer.fit(max_minutes=args.minutes)
    figures.update(
        {
            "preset": args.preset,
            "overrides": args.set,
            "minutes": args.minutes,
            "steps": result.step,
            "rays_per_s": rays_per_s(log_rows(run), result.step, trainer),
            "peak_gpu_memory_gib": peak_gpu_memory_gib(device),
        }
    )
    evaluate(["--run", str(run), "--split", "novel_pose", "--limit", str(args.limit), "--quiet", "--grids", "0"])
    metrics = json.loads((run / "eval" / "metrics.json").read_text())["splits"]["novel_pose"]
    figures.update(
        {
            "novel_pose_psnr": round(metrics["full"]["psnr"], 2),
            "novel_pose_nb_psnr": round(metrics["nb_crop"]["psnr"], 2),
        }
    )
    out = args.out or args.work / "gpu-check.json"
    atomic_write_text(out, json.dumps(figures, indent=1))
    print("gpu-check: " + ", ".join(f"{k} {v}" for k, v in figures.items()))
    return 0 if figures.get("cuda_tests_exit", 0) == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
