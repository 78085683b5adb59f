"""Peak memory and start-up time of ``narf-fit`` against the number of training views (docs/guides/speed.md).

A 1024^2 synthetic capture of 4 frames x 8 cameras (generated once under the benchmark's cache) is listed again and
again in the ``annots.npy`` of a capture with 125 to 1,250 frames, all of them training frames seen by all 8 cameras
(its ``splits.json``): 1k, 5k and 10k training views, at 512^2 (``data.ratio`` 0.5, as Neural Body reads ZJU-MoCap)
and at 1024^2 (ratio 1). Each row is one ``narf-fit`` of one step in a process of its own: its wall time (start-up:
reading every view into the view store, one step, one checkpoint) and its peak resident memory (``wait4``)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pipelines.datasets.smpl_files import cache_dir, command_environment
from pipelines.datasets.zju_mocap import read_annots, write_annots
from pipelines.synthetic.capture import SynthConfig, generate_capture, is_complete

VIEWS = (1000, 5000, 10000)
RATIOS = {512: 0.5, 1024: 1.0}
TEMPLATE = SynthConfig(subject="views", resolution=1024, frames=4, cameras=8, calib_shots=0, calib_close_ups=0)


def many_views(template: Path, out: Path, n_views: int) -> Path:
    """A capture at ``out`` whose frames repeat the template's (symbolic links to its folders), ``n_views`` training
    views in all."""
    cameras, ims = read_annots(template / "annots.npy")
    n_frames = -(-n_views // len(cameras))
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    for entry in template.iterdir():
        if entry.name not in ("annots.npy", "splits.json"):
            (out / entry.name).symlink_to(entry.resolve())
    write_annots(out / "annots.npy", cameras, [ims[f % len(ims)] for f in range(n_frames)])
    splits = {"train_frames": list(range(n_frames)), "novel_frames": [], "train_views": list(range(len(cameras)))}
    (out / "splits.json").write_text(json.dumps(splits | {"test_views": []}))
    return out


def one_step_fit(capture: Path, run_dir: Path, ratio: float) -> tuple[float, float]:
    """(wall seconds, peak RSS in MB) of a one-step ``narf-fit`` of ``capture``."""
    command = [sys.executable, "-m", "pipelines.cli.fit", "--subject", str(capture), "--out", str(run_dir)]
    command += ["--config", "cpu", "--set", "train.steps=1", "--set", f"data.ratio={ratio}"]
    with tempfile.TemporaryFile("w+") as errors:  # a file, not a pipe: a pipe nobody reads fills and blocks the fit
        start = time.perf_counter()
        child = subprocess.Popen(
            command, stdout=subprocess.DEVNULL, stderr=errors, text=True, env=command_environment()
        )
        _, status, usage = os.wait4(child.pid, 0)
        seconds = time.perf_counter() - start
        if status != 0:
            errors.seek(0)
            raise RuntimeError(f"{' '.join(command)} failed: {errors.read()[-2000:]}")
    return seconds, usage.ru_maxrss / 1024


def run() -> list[dict]:
    cache = cache_dir()
    template = cache / "views_template"
    if not is_complete(template):
        generate_capture(template, TEMPLATE, progress=False)
    rows = []
    for size, ratio in RATIOS.items():
        for n_views in VIEWS:
            capture = many_views(template, cache / "views_capture", n_views)
            shutil.rmtree(cache / "views_run", ignore_errors=True)
            seconds, peak = one_step_fit(capture, cache / "views_run", ratio)
            rows.append(
                {
                    "benchmark": "narf-fit start-up",
                    "setting": f"{n_views:,} training views of {size}^2 (one step)",
                    "value": f"{seconds:.0f} s",
                    "peak RSS": f"{peak:.0f} MB",
                }
            )
    return rows
