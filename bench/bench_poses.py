"""The pose correction's harness (docs/guides/fitting.md, *Pose correction*; docs/results/real-capture.md): the
synthetic capture with every joint turned 4 degrees and the body moved 2 cm (``narf-synth --degrade``), the truth
kept beside it.

* **Field fixed**: a field fitted for 3 minutes on the exact poses (``narf-fit``, the ``cpu`` preset, and
  ``cpu_grid`` for the part grids' rows), held fixed while only the perturbed poses are corrected
  (``pipelines.runs.subject.pose_check``), with and without the refinement against the masks first: the joint error
  before, after and along the way.
* **Jointly from scratch**, as a user runs it: ``narf-fit --max-minutes 3`` on the perturbed capture (and on the
  exact one, which must not lose), then ``narf-eval`` on ``same_pose_novel_view`` and ``novel_pose`` and the joint
  error of ``RUN/refined_params`` (``narf-eval --reference-params``).

Takes about 40 minutes on 2 cores and runs only when named (``python -m bench poses``); ``NARF_BENCH_POSES`` (row
labels separated by semicolons) picks rows."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from bench.bench_levers import PERTURBED, SYNTHETIC, _ensure_perturbed, _row, _venv
from pipelines.datasets.smpl_files import cache_dir, command_environment

STEPS = 400
ON = ["train.pose_correction=true"]
#: (label, overrides of the field-fixed correction, frame stride, the field's preset)
FIXED = [
    ("field fixed, photometric only, every 10th frame", ["train.mask_body_iterations=0"], 10, "cpu"),
    (
        "field fixed, photometric only, every 10th frame, every frequency",
        ["train.mask_body_iterations=0", "train.pose_gradient_freqs=10"],
        10,
        "cpu",
    ),
    ("field fixed, photometric only, every frame", ["train.mask_body_iterations=0"], 1, "cpu"),
    ("field fixed, masks then photometric", [], 1, "cpu"),
    ("grid field fixed, photometric only, every 10th frame", ["train.mask_body_iterations=0"], 10, "cpu_grid"),
    (
        "grid field fixed, photometric only, every 10th frame, every level",
        ["train.mask_body_iterations=0", "train.pose_gradient_freqs=10"],
        10,
        "cpu_grid",
    ),
]
#: (label, capture, ``--set`` overrides, minutes)
JOINT = [
    ("exact, no correction", SYNTHETIC, ["train.pose_correction=false"], 3),
    ("exact, pose correction", SYNTHETIC, ON, 3),
    ("perturbed, no correction", PERTURBED, ["train.pose_correction=false"], 3),
    ("perturbed, masks only", PERTURBED, [*ON, "train.pose_start=1000000000"], 3),
    ("perturbed, pose correction", PERTURBED, ON, 3),
]


def _field_run(cache: Path, preset: str) -> Path:
    """The exact-pose field of ``preset`` that the fixed rows hold (fitted once, kept under the bench cache)."""
    run = cache / f"exact-field-{preset}"
    if not (run / "checkpoint.pt").is_file():
        fit = [_venv("narf-fit"), "--subject", str(SYNTHETIC), "--config", preset, "--out", str(run)]
        fit += ["--max-minutes", "3", "--quiet"]
        subprocess.run(fit, check=True, env=command_environment())
    return run


def _fixed_row(label: str, sets: list[str], stride: int, field: Path) -> dict:
    from pipelines.runs.subject.pose_check import PoseCheckRequest, correct_with_field_fixed

    request = PoseCheckRequest(field, PERTURBED, SYNTHETIC, STEPS, tuple(sets), every=STEPS // 4, frame_stride=stride)
    check = correct_with_field_fixed(request)
    return {
        "row": label,
        "steps": STEPS,
        "joint_error_capture_cm": round(check.before, 2),
        "joint_error_run_cm": round(check.after, 2),
        "recovered %": round(100 * check.recovered, 1),
        "path (step: cm)": " ".join(f"{s}: {e:.2f}" for s, e in check.path),
    }


def run() -> list[dict]:
    wanted = {s.strip() for s in os.environ.get("NARF_BENCH_POSES", "").split(";") if s.strip()}
    cache = cache_dir() / "bench-poses"
    _ensure_perturbed()
    rows = []
    for label, sets, stride, preset in FIXED:
        if not wanted or label in wanted:
            rows.append(_fixed_row(label, sets, stride, _field_run(cache, preset)))
    for index, (label, capture, sets, minutes) in enumerate(JOINT):
        if not wanted or label in wanted:
            rows.append(_row(label, capture, sets, minutes, cache / f"run{index}"))
            print(f"bench poses: {label} done", file=sys.stderr)
    return rows
