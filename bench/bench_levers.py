"""The fit's input corrections (docs/model.md §6), each alone and all together, as docs/results/real-capture.md
reports them. Every row is the real commands: ``narf-fit --max-minutes`` then ``narf-eval``.

* The real recording (``make demo-real``'s capture, ``data/real/demo_single_person``, and the same recording prepared
  without the silhouette stage of the body fit, ``--silhouette-iterations 0``, into ``..._keypoints``, and with it
  but the cameras as calibrated, ``--keep-calibration``, into ``..._kept``): 10-minute fits, evaluated on
  ``same_pose_same_view`` (SS), ``novel_pose_same_view`` (NS), ``novel_view`` and ``novel_pose``: NB-crop PSNR, PSNR
  over the person's pixels and the share of crop pixels where render and mask disagree (``narf-eval``'s error
  breakdown).
* The synthetic capture, exact and degraded (``narf-synth --degrade``: every joint turned 4 degrees, the body moved
  2 cm): 3-minute fits (and one of 10), evaluated on ``same_pose_novel_view`` and ``novel_pose`` (full image and NB
  crop), and the mean joint error of the poses the run shows on its training frames against the truth.

Rows whose capture is missing are skipped with a note (``make demo-real`` writes the real one). The full table takes
about two hours on 2 cores: ``NARF_BENCH_LEVERS`` (row labels separated by semicolons) picks rows.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from pipelines.datasets.smpl_files import cache_dir, command_environment

REAL = Path("data/real/demo_single_person")
REAL_KEYPOINTS = Path("data/real/demo_single_person_keypoints")  # prepared with --silhouette-iterations 0
REAL_KEPT = Path("data/real/demo_single_person_kept")  # prepared with --keep-calibration
SYNTHETIC = Path("data/synthetic/taichi")
PERTURBED = Path("data/synthetic/taichi_pose4")
POSE = ["train.pose_correction=true"]
COLOUR = ["train.camera_colour=true"]
BACKGROUND = ["train.random_background=true"]
OFF = ["train.pose_correction=false", "train.camera_colour=false", "train.random_background=false"]
#: (label, capture, ``--set`` overrides of the CPU preset, minutes)
ROWS = [
    ("real, keypoint body, cameras as calibrated", REAL_KEYPOINTS, OFF, 10),
    ("real, silhouette body, cameras as calibrated", REAL_KEPT, OFF, 10),
    ("real, silhouette body and cameras", REAL, OFF, 10),
    ("real, + pose correction", REAL, [*OFF, *POSE], 10),
    ("real, + camera colour", REAL, [*OFF, *COLOUR], 10),
    ("real, + random background", REAL, [*OFF, *BACKGROUND], 10),
    ("real, all three", REAL, [*POSE, *COLOUR, *BACKGROUND], 10),
    ("synthetic exact, no correction", SYNTHETIC, OFF, 3),
    ("synthetic perturbed, no correction", PERTURBED, OFF, 3),
    ("synthetic perturbed, pose correction", PERTURBED, [*OFF, *POSE], 3),
    ("synthetic perturbed, pose correction, 10 minutes", PERTURBED, [*OFF, *POSE], 10),
]
REAL_SPLITS = ("same_pose_same_view", "novel_pose_same_view", "novel_view", "novel_pose")
SYNTHETIC_SPLITS = ("same_pose_novel_view", "novel_pose")
VIEWS = 17


def _venv(name: str) -> str:
    return str(Path(sys.executable).with_name(name))


def _ensure_perturbed() -> None:
    if not (PERTURBED / "degraded.json").is_file():
        subprocess.run([_venv("narf-synth"), "--subject", "taichi"], check=True, env=command_environment())
        subprocess.run(
            [_venv("narf-synth"), "--degrade", str(SYNTHETIC), "--out", str(PERTURBED), "--pose-noise", "4"],
            check=True,
            env=command_environment(),
        )


def _joint_errors(run: Path, truth: Path) -> dict:
    """Mean joint error (cm) of the capture's and of the run's poses on the training frames, against ``truth``."""
    from pipelines.datasets.capture import ZjuCapture
    from pipelines.runs.subject.session import load_run
    from pipelines.synthetic.degrade import joint_errors

    loaded = load_run(run)
    frames = list(loaded.protocol.train_frames)
    reference = ZjuCapture(truth)
    before = joint_errors(reference, loaded.capture, loaded.body_model, frames).mean()
    after = joint_errors(reference, loaded, loaded.body_model, frames).mean()
    return {"joint_error_capture_cm": round(100 * float(before), 2), "joint_error_run_cm": round(100 * float(after), 2)}


def _row(label: str, capture: Path, sets: list[str], minutes: float, out: Path) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    fit = [_venv("narf-fit"), "--subject", str(capture), "--out", str(out), "--max-minutes", str(minutes), "--quiet"]
    subprocess.run([*fit, *(a for s in sets for a in ("--set", s))], check=True, env=command_environment())
    splits = REAL_SPLITS if capture in (REAL, REAL_KEYPOINTS, REAL_KEPT) else SYNTHETIC_SPLITS
    evaluate = [_venv("narf-eval"), "--run", str(out), "--limit", str(VIEWS), "--quiet"]
    subprocess.run(
        [*evaluate, *(a for s in splits for a in ("--split", s))],
        check=True,
        stdout=subprocess.DEVNULL,
        env=command_environment(),
    )
    return measured(label, capture, out)


def measured(label: str, capture: Path, out: Path) -> dict:
    """The row of a fitted and evaluated run folder ``out`` (also for rows measured one by one)."""
    splits = REAL_SPLITS if capture in (REAL, REAL_KEYPOINTS, REAL_KEPT) else SYNTHETIC_SPLITS
    report = json.loads((out / "eval" / "metrics.json").read_text())
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    row = {
        "row": label,
        "steps": log[-1]["step"],
        "rays_per_s": round(float(np.median([r["rays_per_s"] for r in log]))),
    }
    for split in splits:
        crop = report["splits"][split]["nb_crop"]
        breakdown = crop.get("breakdown", {})
        row[f"{split} full PSNR"] = round(report["splits"][split]["full"]["psnr"], 2)
        row[f"{split} NB PSNR"] = round(crop["psnr"], 2)
        row[f"{split} person PSNR"] = round(breakdown.get("psnr_person") or float("nan"), 2)
        row[f"{split} silhouette %"] = round(100 * breakdown.get("pixels_silhouette", float("nan")), 2)
    if capture in (SYNTHETIC, PERTURBED):
        row.update(_joint_errors(out, SYNTHETIC))
    return row


def run() -> list[dict]:
    wanted = {s.strip() for s in os.environ.get("NARF_BENCH_LEVERS", "").split(";") if s.strip()}
    cache = cache_dir() / "bench-levers"
    rows = []
    for index, (label, capture, sets, minutes) in enumerate(ROWS):
        if wanted and label not in wanted:
            continue
        if capture == PERTURBED:
            _ensure_perturbed()
        if not (capture / "annots.npy").is_file():
            print(f"bench levers: {capture} missing; skipped '{label}' (make demo-real prepares it)", file=sys.stderr)
            continue
        rows.append(_row(label, capture, sets, minutes, cache / f"run{index}"))
    return rows
