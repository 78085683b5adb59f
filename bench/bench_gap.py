"""The gap between the training images and the held-out camera (docs/results/real-capture.md, *The CPU
preset, value by value*): a fit's person PSNR, NB crop and silhouette disagreement on its training images (SS), from the
held-out camera (novel_view) and in novel poses from it (novel_pose), and the gap SS - novel_view, for

* the real recording (``make demo-real``'s capture, ``data/real/demo_single_person``), and
* its synthetic analogue with exact inputs: the synthetic taichi capture trained on the three cameras standing where
  the recording's training cameras stand around the person, seen from its held-out camera
  (``python -m pipelines.synthetic.views_like``, written on first use to ``data/synthetic/taichi_like_demo``).

What the recording loses beyond its analogue is the inputs' (calibration, masks, bodies, lighting); what the
analogue loses is the model's. Every row is the real commands: ``narf-fit`` then ``narf-eval``.

Environment: ``NARF_BENCH_GAP`` picks rows (labels separated by semicolons; default: the CPU preset and the paper's
colour on both captures);
``NARF_BENCH_GAP_MINUTES`` (default 10) is each fit's budget, or ``NARF_BENCH_GAP_STEPS`` a fixed step count
instead; ``NARF_BENCH_GAP_JOBS`` fits that many rows at once, each with ``NARF_BENCH_GAP_THREADS`` threads
(defaults 1 and all cores: fixed steps make parallel rows comparable, minutes do not).
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

from pipelines.datasets.smpl_files import cache_dir, command_environment

REAL = Path("data/real/demo_single_person")
SYNTHETIC = Path("data/synthetic/taichi")
ANALOGUE = Path("data/synthetic/taichi_like_demo")
SPLITS = ("same_pose_same_view", "novel_view", "novel_pose")
VIEWS = 17
#: The rows of docs/results/real-capture.md (``--set`` overrides of the CPU preset): the preset as it is (its colour
#: without the view direction), the paper's colour (the preset before), and each lever alone against the paper's
#: colour, as they were measured
PAPER_COLOUR = ["model.view_freqs=4"]
LEVERS = {
    "defaults": [],
    "paper's colour (the preset before)": PAPER_COLOUR,
    "view direction off": ["model.view_freqs=0"],
    "view direction, 1 frequency": ["model.view_freqs=1"],
    "view direction jittered 10 degrees": [*PAPER_COLOUR, "model.view_jitter=10"],
    "view direction jittered 30 degrees": [*PAPER_COLOUR, "model.view_jitter=30"],
    "pose features dropped half the time": [*PAPER_COLOUR, "model.pose_dropout=0.5"],
    "coarse-to-fine over 2,000 steps": [*PAPER_COLOUR, "train.window_steps=2000"],
    "view direction off, coarse-to-fine": ["model.view_freqs=0", "train.window_steps=2000"],
    "ray entropy on virtual cameras": [*PAPER_COLOUR, "train.entropy_weight=0.002"],
    "held-back frames choose the step": [*PAPER_COLOUR, "train.holdout_every=10"],
    # against the preset as it is now (its colour without the view direction)
    "defaults, mask weight 3": ["train.mask_weight=3"],
    "defaults, appearance code per frame": ["model.appearance_dim=8"],
    "defaults, depth smoothness on virtual patches": ["train.smoothness_weight=0.1"],
    "defaults, pose in the colour at 1 frequency": ["model.pose_freqs=1"],
    "defaults, no pose in the colour": ["model.pose_freqs=0"],
    "defaults, 40 % of the rays on the silhouette band": ["train.body_fraction=0.5", "train.border_fraction=0.4"],
    "defaults, pseudo-Huber colour loss at 0.05": ["train.colour_delta=0.05"],
    "defaults, pseudo-Huber colour loss at 0.2": ["train.colour_delta=0.2"],
    "defaults, pose correction": ["train.pose_correction=true"],
}
#: (label, capture, overrides): every row on the recording and on its analogue
ROWS = [(f"real, {name}", REAL, sets) for name, sets in LEVERS.items()] + [
    (f"analogue, {name}", ANALOGUE, sets) for name, sets in LEVERS.items()
]
DEFAULT_ROWS = tuple(f"{capture}, {name}" for capture in ("real", "analogue") for name in list(LEVERS)[:2])


def _venv(name: str) -> str:
    return str(Path(sys.executable).with_name(name))


def _ensure_analogue() -> None:
    if (ANALOGUE / "splits.json").is_file():
        return
    if not (SYNTHETIC / "annots.npy").is_file():
        subprocess.run([_venv("narf-synth"), "--subject", "taichi"], check=True, env=command_environment())
    command = [sys.executable, "-m", "pipelines.synthetic.views_like", str(SYNTHETIC), str(REAL), str(ANALOGUE)]
    subprocess.run(command, check=True, env=command_environment())


def _budget() -> list[str]:
    steps = os.environ.get("NARF_BENCH_GAP_STEPS")
    if steps:
        return ["--set", f"train.steps={int(steps)}"]
    return ["--max-minutes", os.environ.get("NARF_BENCH_GAP_MINUTES", "10")]


def _row(label: str, capture: Path, sets: list[str], out: Path, env: dict) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    fit = [_venv("narf-fit"), "--subject", str(capture), "--out", str(out), "--quiet", *_budget()]
    subprocess.run([*fit, *(a for s in sets for a in ("--set", s))], check=True, env=env)
    evaluate = [_venv("narf-eval"), "--run", str(out), "--limit", str(VIEWS), "--quiet"]
    evaluate += [a for s in SPLITS for a in ("--split", s)]
    subprocess.run(evaluate, check=True, stdout=subprocess.DEVNULL, env=env)
    return measured(label, out)


def measured(label: str, out: Path) -> dict:
    """The row of a fitted and evaluated run folder ``out``: person PSNR (low-passed too, with the view's best
    colour gains, and on the surfaces no training view saw, with their share of the person: docs/model.md §7), NB
    crop and silhouette per split, the gap."""
    report = json.loads((out / "eval" / "metrics.json").read_text())
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    row = {
        "row": label,
        "steps": log[-1]["step"],
        "kept step": report.get("step"),
        "rays_per_s": round(float(np.median([r["rays_per_s"] for r in log if "rays_per_s" in r]))),
    }
    person = {}
    for split in SPLITS:
        crop = report["splits"][split]["nb_crop"]
        breakdown = crop.get("breakdown", {})
        person[split] = breakdown.get("psnr_person") or float("nan")
        row[f"{split} person PSNR"] = round(person[split], 2)
        row[f"{split} person PSNR low-passed"] = round(breakdown.get("psnr_person_coarse") or float("nan"), 2)
        row[f"{split} person PSNR, best gains"] = round(breakdown.get("psnr_person_gain") or float("nan"), 2)
        row[f"{split} NB PSNR"] = round(crop["psnr"], 2)
        row[f"{split} silhouette %"] = round(100 * breakdown.get("pixels_silhouette", float("nan")), 2)
        row[f"{split} unseen surface %"] = round(100 * breakdown.get("pixels_unseen", float("nan")), 2)
        row[f"{split} person PSNR, unseen surface"] = round(breakdown.get("psnr_person_unseen") or float("nan"), 2)
    row["gap SS - novel_view (dB)"] = round(person["same_pose_same_view"] - person["novel_view"], 2)
    return row


def run() -> list[dict]:
    wanted = {s.strip() for s in os.environ.get("NARF_BENCH_GAP", ";".join(DEFAULT_ROWS)).split(";") if s.strip()}
    cache = cache_dir() / "bench-gap"
    jobs = int(os.environ.get("NARF_BENCH_GAP_JOBS", "1"))
    env = command_environment()
    if os.environ.get("NARF_BENCH_GAP_THREADS"):
        env["OMP_NUM_THREADS"] = os.environ["NARF_BENCH_GAP_THREADS"]
    if not (REAL / "annots.npy").is_file():
        print(f"bench gap: {REAL} missing (make demo-real prepares it); nothing measured", file=sys.stderr)
        return []
    _ensure_analogue()
    chosen = [(index, row) for index, row in enumerate(ROWS) if row[0] in wanted]
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        futures = [
            pool.submit(_row, label, capture, sets, cache / f"run{i}", env) for i, (label, capture, sets) in chosen
        ]
        return [future.result() for future in futures]
