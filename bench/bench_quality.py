"""Time to quality: minutes of fitting until the synthetic taichi capture's ``novel_pose_novel_view`` split reaches
26 / 28 / 30 dB full-image PSNR and 22 / 24 dB in the Neural Body crop.

Each configuration is fitted with the real commands (``narf-fit --max-minutes``, resumed slice by slice) and
evaluated after every slice with ``narf-eval --split novel_pose_novel_view --limit VIEWS``; a threshold's time is
the fitting time of the first evaluation that reaches it (so it is only as fine as the slices). Minutes count
fitting only. The capture is the default ``narf-synth`` one in the data root, generated there when missing; the
last row fits the preset on a 240-frame capture (``narf-synth --frames 240``, generated under the benchmark's cache),
the capture on which the speed targets' starting point (23.7 dB NB crop after 10 minutes) was measured: its held-out
poses are the last 24 of a shorter motion, closer to the training poses than the default capture's last 30.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

from fitting.files import atomic_write_text
from pipelines.datasets.smpl_files import cache_dir, command_environment

#: (row label, ``--set`` overrides of the CPU preset, frames of the capture: None = the default capture)
SIXTEEN = ["render.train_coarse=16", "render.train_fine=16"]
CONFIGS = [
    ("NARF_D cpu preset (8+8, occupancy grid, grid proposal)", [], None),
    ("NARF_D 8+8, occupancy grid, coarse field pass", ["render.grid_proposal=false"], None),
    ("NARF_D 8+8, box bounds", ["render.occupancy=false", "render.grid_proposal=false"], None),
    (
        "NARF_D 16+16, box bounds (the preset before the grid)",
        [*SIXTEEN, "render.occupancy=false", "render.grid_proposal=false"],
        None,
    ),
    ("NARF_D cpu preset on the 240-frame capture", [], 240),
]
SLICES = (1, 2, 3, 5, 10)  #: cumulative minutes of fitting at which the split is evaluated
VIEWS = 17  #: evaluated views (spread over the held-out poses and test cameras)
FULL_DB, CROP_DB = (26, 28, 30), (22, 24)


def _run(args: list[str]) -> None:
    """Run a console script (``pipelines.cli.<name>``, then its arguments) as a user would."""
    code = f"from {args[0]} import entrypoint; entrypoint()"
    command = [sys.executable, "-c", code, *args[1:]]
    done = subprocess.run(command, capture_output=True, text=True, env=command_environment())
    if done.returncode != 0:
        lines = done.stderr.strip().splitlines()
        raise RuntimeError(lines[-1] if lines else f"{args[0]} failed with code {done.returncode}")


def _run_dir(root: Path, label: str) -> Path:
    return root / label.replace(" ", "_").replace(",", "").replace("+", "plus")


def _curve(label: str, overrides: list[str], root: Path, data_dir: Path) -> list[dict]:
    """Fit slice by slice; returns one record per slice (minutes, steps, PSNRs, median rays/s)."""
    run = _run_dir(root, label)
    if run.exists():  # a fresh fit every time: earlier slices would not be timed on this machine
        shutil.rmtree(run)
    data = ["--data-root", str(data_dir)]
    sets = [item for pair in zip(["--set"] * len(overrides), overrides) for item in pair]
    records, done = [], 0.0
    for minutes in SLICES:
        resume = ["--resume"] if (run / "checkpoint.pt").exists() else [*data, *sets]
        _run(["pipelines.cli.fit", "--out", str(run), *resume, "--max-minutes", str(minutes - done), "--quiet"])
        done = minutes
        _run(["pipelines.cli.eval", "--run", str(run), "--split", "novel_pose_novel_view", "--limit", str(VIEWS)])
        split = json.loads((run / "eval" / "metrics.json").read_text())["splits"]["novel_pose_novel_view"]
        log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
        rates = sorted(row["rays_per_s"] for row in log)
        records.append(
            {
                "minutes": minutes,
                "steps": log[-1]["step"],
                "full": split["full"]["psnr"],
                "crop": split["nb_crop"]["psnr"],
                "rays/s": rates[len(rates) // 2],
            }
        )
    return records


def render_seconds(run_dir: Path) -> dict[int, float]:
    """Seconds to render one held-out view of a fitted run (first ``novel_pose_novel_view`` item) at 256^2 and
    512^2 (the camera's intrinsics scaled), evaluation sample counts, 2 threads; best of two."""
    import dataclasses
    import time

    import numpy as np
    import torch

    from fitting.evaluate import render_view
    from pipelines.runs.subject.session import load_run, poses_for_frames

    torch.set_num_threads(2)
    run = load_run(run_dir)
    frame, cam = run.protocol.split("novel_pose_novel_view")[0]
    camera = run.capture.load_frame(frame, cam).camera
    poses, _, _ = poses_for_frames(run, run.body_model, [frame])
    seconds = {}
    for size in (256, 512):
        scale = np.diag([size / camera.width, size / camera.height, 1.0])
        view = dataclasses.replace(camera, K=scale @ camera.K, width=size, height=size)
        times = []
        for _ in range(2):
            start = time.perf_counter()
            render_view(run.field, view, poses, run.config)
            times.append(time.perf_counter() - start)
        seconds[size] = min(times)
    return seconds


def _first(records: list[dict], key: str, level: float) -> str:
    reached = [r["minutes"] for r in records if r[key] >= level]
    return f"{reached[0]} min" if reached else f"> {records[-1]['minutes']} min"


#: ``python -m bench --reuse`` also takes this benchmark's finished configurations back (``run(reuse=True)``)
KEEPS_CONFIGURATIONS = True


def run(configs: list[tuple[str, list[str], int | None]] | None = None, reuse: bool = False) -> list[dict]:
    """One row per configuration (``CONFIGS`` by default); ``reuse``: a configuration's row saved on this machine is
    taken instead of fitting it again."""
    cache = cache_dir()
    return [
        _row(label, overrides, cache / "quality_runs", _capture_root(cache, frames), reuse)
        for label, overrides, frames in configs or CONFIGS
    ]


def _capture_root(cache: Path, frames: int | None) -> Path:
    """The data root holding the synthetic taichi capture of ``frames`` frames (the user's data root for the default
    capture, the benchmark's cache otherwise), generated there by ``narf-synth`` when missing."""
    from pipelines.datasets.subjects import data_root
    from pipelines.synthetic.capture import is_complete

    data_dir = data_root(None) if frames is None else cache / f"taichi_{frames}_frames"
    if not is_complete(data_dir / "synthetic" / "taichi"):
        # in its own process, as a user runs it: the generator forks render workers, and a child forked from this
        # process, whose torch and OpenCV thread pools have run in the benchmarks before, can hang
        extra = [] if frames is None else ["--frames", str(frames)]
        _run(["pipelines.cli.synth", "--subject", "taichi", "--data-root", str(data_dir), *extra])
    return data_dir


def _row(label: str, overrides: list[str], root: Path, data_dir: Path, reuse: bool = False) -> dict:
    """One configuration's row, saved as ``row.json`` in its run folder once complete; with ``reuse`` (``python -m
    bench --reuse``) a row saved on this machine is taken instead of fitting again."""
    from bench.bench_models import machine

    saved = _run_dir(root, label) / "row.json"
    if reuse and saved.exists():
        record = json.loads(saved.read_text())
        if record.get("machine") == machine():
            return record["row"]
    try:
        records = _curve(label, overrides, root, data_dir)
    except RuntimeError as err:
        return {"model": f"{label}: time to quality", "params": f"failed: {err}"}
    last = records[-1]
    row = {"model": f"{label}: time to quality", "train rays/s fp32": f"{last['rays/s']:,.0f} (fit median)"}
    row.update({f"min to {db} dB full": _first(records, "full", db) for db in FULL_DB})
    row.update({f"min to {db} dB NB crop": _first(records, "crop", db) for db in CROP_DB})
    times = render_seconds(_run_dir(root, label))
    row.update({f"render {size}^2 s (fitted)": f"{t:.2f}" for size, t in times.items()})
    curve = ", ".join(f"{r['minutes']}: {r['full']:.2f}/{r['crop']:.2f}" for r in records)
    row["NN PSNR full/crop by minute"] = curve
    atomic_write_text(saved, json.dumps({"machine": machine(), "row": row}, indent=1))
    return row
