"""Run a table of the supplement (``narf-experiments run``): fit every row with ``pipelines.runs.fit.fit`` (what
``narf-fit`` runs) for a time budget, evaluate it with the table's protocol, and write the table (Markdown + JSON)
with its cost columns.

Layout under ``OUT/<table>/``: ``<row>/run/`` (the row's run folder), ``<row>/result.json`` (written atomically
once the row is evaluated: a finished row is never recomputed), ``table.json`` and ``table.md``. A killed row
resumes from its checkpoint with the rest of its budget (the checkpoint stores the training time spent).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from fitting.checkpoint import load_checkpoint
from fitting.config import load_config
from fitting.files import atomic_write_text, folder_lock
from fitting.fitted import SavedRun, read_run
from fitting.model_setup import make_field
from fitting.run_folder import auto_device
from pipelines.experiments.orderings import check_orderings
from pipelines.experiments.tables import SHORT, Row, Table
from pipelines.runs.fit import fit
from pipelines.runs.kinds import RUN_KINDS
from pipelines.runs.requests import EvalRequest, FitRequest

#: CPU budget per row in minutes, and views per split evaluated, per table: the budgets of the committed results
#: (README, "Experiments"), so that the default command reproduces them.
CPU_BUDGET = {"table-a": 5.0, "table-b": 5.0, "table-c": 3.0}
CPU_VIEWS = {"table-a": 20, "table-b": None, "table-c": 6}


@dataclass(frozen=True)
class Settings:
    """How a table runs: ``preset`` cpu or paper, ``budget_minutes`` of training per row (None: the preset's
    steps), ``limit`` views per split (None: all), ``data_root`` and ``device`` passed to the commands."""

    preset: str = "cpu"
    budget_minutes: float | None = None
    limit: int | None = None
    data_root: str | None = None
    device: str = "auto"


def fit_request(table: Table, row: Row, settings: Settings, run_dir: Path) -> FitRequest:
    """The fit of a row: a fresh one at the table's preset (``preset`` cpu: the kind's CPU preset, paper: its CUDA
    one; the CNN baseline has its own), or a resumed one with the rest of its budget."""
    budget = settings.budget_minutes
    common = {"out": run_dir, "device": settings.device, "progress": False}
    if (run_dir / "checkpoint.pt").is_file():
        if budget is not None:
            budget = max(budget - load_checkpoint(run_dir).get("elapsed", 0.0) / 60, 0.0)
        return FitRequest(resume=True, max_minutes=budget, **common)
    preset = RUN_KINDS[table.kind].preset(row.fit.model, settings.preset == "paper")
    return FitRequest(
        preset=preset,
        kind=table.kind,
        model=row.fit.model,
        data_root=settings.data_root,
        overrides=row.fit.sets,
        max_minutes=budget,
        **common,
    )


def _finished(run_dir: Path, settings: Settings) -> bool:
    if not (run_dir / "checkpoint.pt").is_file():
        return False
    state = load_checkpoint(run_dir)
    if settings.budget_minutes is not None:
        return state.get("elapsed", 0.0) >= settings.budget_minutes * 60 - 1.0
    return state["step"] >= state["config"]["train"]["steps"]


def run_fit(table: Table, row: Row, settings: Settings, run_dir: Path) -> None:
    """Fit (or resume) a row until its budget is spent; Ctrl-C stops the table with the checkpoint saved."""
    while not _finished(run_dir, settings):
        fit(fit_request(table, row, settings, run_dir))
        if settings.budget_minutes is None:
            return


def evaluate(table: Table, run: Path | SavedRun, settings: Settings) -> dict:
    """The table's protocol on a fitted row (its folder, or its checkpoint already read): split -> {mask_l2, psnr,
    ssim} (full image)."""
    request = EvalRequest(tuple(table.splits), settings.limit, str(auto_device(settings.device)), progress=False)
    report = RUN_KINDS[table.kind].evaluate(run, request)
    return {split: report["splits"][split]["full"] for split in table.splits}


def row_costs(run: Path | SavedRun) -> dict:
    """#params, FLOPs and activation memory per ray of the fitted model (docs/model.md §8), its training steps,
    seconds and median rays/s from the run's log."""
    saved = read_run(run)
    run_dir, state = saved.run_dir, saved.state
    model = make_field(saved.config)
    cost = model.cost() if hasattr(model, "cost") else None
    log_path = run_dir / "log.jsonl"  # absent when the fit ran fewer steps than train.log_every
    log = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()] if log_path.is_file() else []
    rates = [row["rays_per_s"] for row in log if "rays_per_s" in row]
    return {
        "params": sum(p.numel() for p in model.parameters()),
        "flops_per_ray": cost.flops_per_ray if cost else None,
        "memory_per_ray": cost.memory_per_ray if cost else None,
        "steps": state["step"],
        "train_seconds": state.get("elapsed", 0.0),
        "rays_per_s": float(np.median(rates)) if rates else None,
    }


def run_row(table: Table, row: Row, out_dir: Path, settings: Settings, fitter=run_fit, evaluator=evaluate) -> dict:
    """One row, resumable: the stored result when the row finished before, else fit, evaluate and store."""
    result_path = out_dir / row.name / "result.json"
    if result_path.is_file():
        return json.loads(result_path.read_text())
    run_dir = out_dir / row.name / "run"
    start = time.perf_counter()
    fitter(table, row, settings, run_dir)
    saved = read_run(run_dir)  # the fitted checkpoint, read once for the evaluation and the costs
    metrics = evaluator(table, saved, settings)
    result = {
        "row": row.name,
        "label": row.label,
        "fit_args": list(row.fit_args),
        "preset": settings.preset,
        "budget_minutes": settings.budget_minutes,
        "views_per_split": settings.limit,
        "metrics": metrics,
        "cost": row_costs(saved),
        "wall_seconds": time.perf_counter() - start,
    }
    atomic_write_text(result_path, json.dumps(result, indent=1))
    return result


def prepare_data(table: Table, settings: Settings) -> None:
    """Find the table's data before the first row (generating the synthetic stand-in, with its progress bar, when
    it is missing), so that the rows' quiet fits do not wait on it silently."""
    kind = RUN_KINDS[table.kind]
    overrides = [] if settings.data_root is None else [f"data.data_root={settings.data_root}"]
    kind.data(load_config(kind.presets[0], overrides))


def check_settings(out_dir: Path, settings: Settings) -> None:
    """Keep one table's rows comparable: the first run records its settings in ``settings.json``; a later run with
    another preset, budget, view count or data root is refused (the device may change)."""
    path = out_dir / "settings.json"
    current = {k: v for k, v in asdict(settings).items() if k != "device"}
    if path.is_file():
        stored = json.loads(path.read_text())
        changed = sorted(k for k in current if stored.get(k) != current[k])
        if changed:
            raise ValueError(
                f"{path}: this table was run with {', '.join(f'{k}={stored.get(k)}' for k in changed)}; rerun with "
                "the same settings to resume it, or choose another --out"
            )
    else:
        atomic_write_text(path, json.dumps(current, indent=1))


def run_table(table: Table, out: Path, settings: Settings, rows: list[str] | None = None, progress=print, **kw) -> dict:
    """Run (or resume) the rows of a table, then write ``table.json`` and ``table.md`` under ``out/<table>``. One
    process runs a table's folder at a time (``fitting.files.folder_lock``)."""
    with folder_lock(Path(out) / table.name):
        return _run_table(table, Path(out) / table.name, settings, rows, progress, **kw)


def _run_table(table: Table, out_dir: Path, settings: Settings, rows, progress, **kw) -> dict:
    check_settings(out_dir, settings)
    chosen = [r for r in table.rows if rows is None or r.name in rows]
    results = {}
    for k, row in enumerate(chosen):
        done = (out_dir / row.name / "result.json").is_file()
        progress(f"narf-experiments: {table.name} row {k + 1}/{len(chosen)} {row.name}" + (" (done)" if done else ""))
        results[row.name] = run_row(table, row, out_dir, settings, **kw)
    summary = {
        "table": table.name,
        "title": table.title,
        "settings": asdict(settings),
        "rows": results,
        "orderings": check_orderings(table.name, {n: r["metrics"] for n, r in results.items()}),
    }
    atomic_write_text(out_dir / "table.json", json.dumps(summary, indent=1))
    atomic_write_text(out_dir / "table.md", markdown_table(table, summary))
    return summary


def cell_text(m: dict) -> str:
    """One table cell: Mask L2 (x10^4) / PSNR (dB) / SSIM."""
    return f"{m['mask_l2']:.1f}/{m['psnr']:.2f}/{m['ssim']:.4f}"


def _si(value: float | None) -> str:
    if value is None:
        return "-"
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "K")):
        if abs(value) >= scale:
            return f"{value / scale:.2f}{suffix}"
    return f"{value:.0f}"


def _preset_names(table: Table, preset: str) -> str:
    """The presets a table's rows ran with (``preset`` cpu or paper): the kind's, and the CNN's where it has a row."""
    kind, gpu = RUN_KINDS[table.kind], preset == "paper"
    names = dict.fromkeys(kind.preset(row.fit.model, gpu) for row in table.rows)
    return " / ".join(names) + f" ({preset})"


def markdown_table(table: Table, summary: dict) -> str:
    """Supplement layout: method, cost (#params / FLOPs / memory per ray), training, then a cell per split."""
    s = summary["settings"]
    budget = "preset steps" if s["budget_minutes"] is None else f"{s['budget_minutes']:g} min"
    heads = " | ".join(SHORT[x] for x in table.splits)
    lines = [
        f"# {table.title}",
        "",
        f"Preset {_preset_names(table, s['preset'])}, training budget {budget} per row, views per split: "
        f"{s['limit'] or 'all'}. "
        "Cells: Mask L2 (x10^4) / PSNR (dB) / SSIM, full image.",
        "",
        f"| method | #params / FLOPs / memory per ray | steps (rays/s) | {heads} |",
        "|---|---|---|" + "---|" * len(table.splits),
    ]
    for row in summary["rows"].values():
        c = row["cost"]
        cost = f"{_si(c['params'])} / {_si(c['flops_per_ray'])} / {_si(c['memory_per_ray'])}"
        rate = "-" if c["rays_per_s"] is None else f"{c['rays_per_s']:,.0f}"
        cells = " | ".join(cell_text(row["metrics"][x]) for x in table.splits)
        lines.append(f"| {row['label']} | {cost} | {c['steps']:,} ({rate}) | {cells} |")
    lines += ["", "Orderings of the supplement:", ""]
    for o in summary["orderings"]:
        verdict = {True: "reproduced", False: "not reproduced", None: "not checked"}[o["holds"]]
        lines.append(f"* {o['claim']}: **{verdict}** ({o['evidence']})")
    lines += ["", *(f"Note: {n}" for n in table.notes), ""]
    return "\n".join(lines)
