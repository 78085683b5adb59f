"""Time to quality of two CPU presets side by side (docs/results/detail.md): for each capture and each budget of
minutes, the two presets are fitted at once, one thread each (``OMP_NUM_THREADS=1``), then evaluated at once, with
the real commands (``narf-fit --max-minutes``, ``narf-eval``). A row per capture, preset and budget: steps and the
step's cost, and the NB crop and person PSNR on the training images (``same_pose_same_view``), from the held-out
cameras (``novel_view``) and in novel poses (``novel_pose``).

Captures: the synthetic taichi capture with exact inputs (``narf-synth --subject taichi``) under Neural Body's
protocol (``data.protocol=neuralbody``, trained on the band's colours as that protocol's fits are:
``train.random_background=false``), and the real demo (``make demo-real``'s capture,
``data/real/demo_single_person``), skipped with a line when missing.

Environment: ``NARF_BENCH_DETAIL_PRESETS`` (default ``cpu,cpu_grid``: the default preset, and the same with the
part grids), ``NARF_BENCH_DETAIL_MINUTES`` (default ``1,3,10``), ``NARF_BENCH_DETAIL_CAPTURES`` (default
``synthetic,real``), ``NARF_BENCH_DETAIL_VIEWS`` (views a split, default 17), ``NARF_BENCH_DETAIL_REAL`` (the real
capture's folder). About an hour and a half with the defaults; on request only (``python -m bench detail``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import yaml

from pipelines.datasets.smpl_files import cache_dir, command_environment

SPLITS = ("same_pose_same_view", "novel_view", "novel_pose")
CAPTURES = {
    # Neural Body's protocol scores the mask's band in the capture's own colours, and its fits learn them there:
    # trained so here (no random background) whatever the preset says (docs/results/detail.md, "Now")
    "synthetic": (Path("data/synthetic/taichi"), ["data.protocol=neuralbody", "train.random_background=false"]),
    "real": (Path(os.environ.get("NARF_BENCH_DETAIL_REAL", "data/real/demo_single_person")), []),
}


def _venv(name: str) -> str:
    return str(Path(sys.executable).with_name(name))


def _listed(variable: str, default: str) -> list[str]:
    return [item.strip() for item in os.environ.get(variable, default).split(",") if item.strip()]


def _fit(capture: Path, sets: list[str], preset: str, minutes: float, out: Path, env: dict) -> None:
    shutil.rmtree(out, ignore_errors=True)
    command = [_venv("narf-fit"), "--subject", str(capture), "--config", preset, "--out", str(out), "--quiet"]
    command += ["--max-minutes", str(minutes), *(a for s in sets for a in ("--set", s))]
    subprocess.run(command, check=True, env=env, stdout=subprocess.DEVNULL)


def _evaluate(out: Path, views: int, env: dict) -> None:
    command = [_venv("narf-eval"), "--run", str(out), "--limit", str(views), "--quiet", "--grids", "0"]
    command += [a for s in SPLITS for a in ("--split", s)]
    subprocess.run(command, check=True, env=env, stdout=subprocess.DEVNULL)


def measured(label: dict, out: Path) -> dict:
    """The row of a fitted and evaluated run folder: steps, the median step's milliseconds, NB crop and person PSNR
    of each split."""
    report = json.loads((out / "eval" / "metrics.json").read_text())
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    rays = [row["rays_per_s"] for row in log if "rays_per_s" in row]
    train = yaml.safe_load((out / "config.yaml").read_text())["train"]
    step_rays = train["images_per_step"] * train["rays_per_image"]
    row = {**label, "steps": log[-1]["step"], "ms / step": round(1e3 * step_rays / float(np.median(rays)), 1)}
    for split in SPLITS:
        crop = report["splits"][split]["nb_crop"]
        row[f"{split} NB crop"] = round(crop["psnr"], 2)
        row[f"{split} person"] = round(crop.get("breakdown", {}).get("psnr_person") or float("nan"), 2)
    return row


def _pair(capture_name: str, presets: list[str], minutes: float, cache: Path, views: int) -> list[dict]:
    """The presets fitted side by side for ``minutes`` on one capture, one thread each, then evaluated side by side."""
    capture, sets = CAPTURES[capture_name]
    env = command_environment(OMP_NUM_THREADS="1")
    outs = [cache / f"{capture_name}_{preset}_{minutes:g}min" for preset in presets]
    with ThreadPoolExecutor(max_workers=len(presets)) as pool:
        list(pool.map(lambda job: _fit(capture, sets, job[0], minutes, job[1], env), zip(presets, outs)))
        list(pool.map(lambda out: _evaluate(out, views, env), outs))
    labels = [{"capture": capture_name, "preset": preset, "minutes": minutes} for preset in presets]
    return [measured(label, out) for label, out in zip(labels, outs)]


def run() -> list[dict]:
    presets = _listed("NARF_BENCH_DETAIL_PRESETS", "cpu,cpu_grid")
    budgets = [float(m) for m in _listed("NARF_BENCH_DETAIL_MINUTES", "1,3,10")]
    views = int(os.environ.get("NARF_BENCH_DETAIL_VIEWS", "17"))
    cache = cache_dir() / "bench-detail"
    rows = []
    for name in _listed("NARF_BENCH_DETAIL_CAPTURES", "synthetic,real"):
        if not (CAPTURES[name][0] / "annots.npy").is_file():
            print(f"bench detail: {CAPTURES[name][0]} missing; {name} not measured", file=sys.stderr)
            continue
        for minutes in budgets:
            rows += _pair(name, presets, minutes, cache, views)
            print(f"bench detail: {name}, {minutes:g} min done", file=sys.stderr, flush=True)
    return rows
