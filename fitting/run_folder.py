"""The run folder and the device: what a run folder may hold, how one is created or taken up again, where its
config is written, how its log is cut back to a resumed step, and which device a device name means
(docs/guides/fitting.md, "The run folder")."""

from __future__ import annotations

import json
from pathlib import Path

import torch
import yaml

from fitting.config import FitConfig
from fitting.files import atomic_write_text


def auto_device(name: str = "auto") -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device '{name}' requested but CUDA is not available")
    return torch.device(name)


#: What a run folder holds (hidden names too: a checkpoint being written); anything else means it is not one.
RUN_ENTRIES = frozenset(
    {
        "checkpoint.pt",
        "config.yaml",
        "log.jsonl",
        "curve.png",
        "val",
        "eval",
        "videos",
        "meshes",
        "viewer",
        "refined_params",
        "body_model.json",
    }
)


def prepare_run_dir(out: Path, resume: bool, write: bool = True) -> Path:
    """Create the run folder, refusing a file, a folder that holds a fit unless resuming, and a folder that holds
    anything a run does not write; a new fit's old ``log.jsonl`` goes. ``write=False`` (data-parallel ranks other
    than 0) only checks. ``config.yaml`` is the trainer's to write (:func:`write_config`)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: output path exists and is a file")
    if not resume and out.is_dir() and (out / "checkpoint.pt").exists():
        raise FileExistsError(f"{out}: holds a fit already; pass --resume to continue it or choose another --out")
    foreign = (
        sorted(p.name for p in out.iterdir() if p.name not in RUN_ENTRIES and not p.name.startswith("."))
        if out.is_dir()
        else []
    )
    if foreign:
        raise FileExistsError(
            f"{out}: not a run folder (it holds {', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}); "
            "choose a new or empty --out"
        )
    out.mkdir(parents=True, exist_ok=True)
    if not resume and write:
        (out / "log.jsonl").unlink(missing_ok=True)
    return out


def write_config(run_dir: Path, config: FitConfig) -> None:
    """``run_dir/config.yaml``: the config as run, atomically."""
    atomic_write_text(Path(run_dir) / "config.yaml", yaml.safe_dump(config.to_dict(), sort_keys=False))


def add_to_last_row(path: Path, step: int, values: dict) -> bool:
    """Merge ``values`` into the last row of a ``log.jsonl`` when that row is ``step``'s, rewriting the file
    atomically (each step appears once); False, and nothing written, when the last row is another step's or there is
    none (the caller appends a row of its own)."""
    if not path.is_file():
        return False
    lines = path.read_text().splitlines()
    try:
        last = json.loads(lines[-1]) if lines else None
    except json.JSONDecodeError:
        return False
    if not isinstance(last, dict) or last.get("step") != step:
        return False
    lines[-1] = json.dumps({**last, **values})
    atomic_write_text(path, "".join(f"{line}\n" for line in lines))
    return True


def trim_log(path: Path, step: int) -> None:
    """Drop the rows of a ``log.jsonl`` past ``step`` and a last row cut short, rewriting it atomically: a fit
    resumed from its checkpoint at ``step`` logs those steps again, and each step must appear once, in order."""
    if not path.is_file():
        return
    lines = path.read_text().splitlines()
    kept = []
    for line in lines:
        try:
            row = json.loads(line)
        except json.JSONDecodeError:  # a row the killed process was writing
            continue
        if isinstance(row, dict) and row.get("step", 0) <= step:
            kept.append(line)
    if len(kept) != len(lines):
        atomic_write_text(path, "".join(f"{line}\n" for line in kept))
