"""``narf-experiments compare``: a table's results beside the supplement's numbers, row by row, and for each of the
supplement's orderings whether the results reproduce it (``pipelines.experiments.orderings``)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from pipelines.experiments.orderings import check_orderings, paper_results
from pipelines.experiments.runner import cell_text
from pipelines.experiments.tables import SHORT, TABLES


def load_summary(path: str | Path) -> dict:
    """A ``table.json`` written by ``narf-experiments run`` (or the folder that holds it).

    Raises:
        ValueError: not such a file, or not a table of this project.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "table.json"
    try:
        summary = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a readable table.json ({err})") from err
    if not isinstance(summary, dict) or summary.get("table") not in TABLES or not isinstance(summary.get("rows"), dict):
        raise ValueError(f"{path}: not a table written by narf-experiments run (no known 'table' and 'rows')")
    for name, row in summary["rows"].items():
        _check_row(path, name, row, TABLES[summary["table"]].splits)
    return summary


def _check_row(path: Path, name: str, row, splits) -> None:
    """A row as ``narf-experiments run`` writes it: a label and, per split of the table, finite metrics."""
    where = f"{path}: rows['{name}']"
    if not isinstance(row, dict) or not isinstance(row.get("label"), str) or not isinstance(row.get("metrics"), dict):
        raise ValueError(f"{where} needs a 'label' (text) and 'metrics' (an object per split)")
    for split in splits:
        cell = row["metrics"].get(split)
        if not isinstance(cell, dict):
            raise ValueError(f"{where}['metrics'] lacks the split '{split}'")
        for key in ("mask_l2", "psnr", "ssim"):
            value = cell.get(key)
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"{where}['metrics']['{split}']['{key}'] is {value!r}, not a finite number")


def _delta(ours: dict, paper: dict) -> str:
    return f"{ours['psnr'] - paper['psnr']:+.2f} dB"


def compare_markdown(summary: dict) -> str:
    """Per row and split: ours | supplement | PSNR difference; then the orderings on ours and on the supplement."""
    table = TABLES[summary["table"]]
    paper = paper_results(table)
    lines = [f"# {table.title}: this run beside the supplement", "", "Cells: Mask L2 (x10^4) / PSNR (dB) / SSIM.", ""]
    lines += ["| method | split | ours | supplement | PSNR ours - supplement |", "|---|---|---|---|---|"]
    for name, row in summary["rows"].items():
        for split in table.splits:
            ours = row["metrics"][split]
            ref = paper.get(name, {}).get(split)
            ref_text, delta = (cell_text(ref), _delta(ours, ref)) if ref else ("-", "-")
            lines.append(f"| {row['label']} | {SHORT[split]} | {cell_text(ours)} | {ref_text} | {delta} |")
    ours = check_orderings(table.name, {n: r["metrics"] for n, r in summary["rows"].items()})
    theirs = check_orderings(table.name, paper)
    lines += ["", "| ordering | supplement | this run | evidence (this run) |", "|---|---|---|---|"]
    word = {True: "holds", False: "does not hold", None: "not checked"}
    for o, p in zip(ours, theirs):
        lines.append(f"| {o['claim']} | {word[p['holds']]} | **{word[o['holds']]}** | {o['evidence']} |")
    return "\n".join(lines) + "\n"
