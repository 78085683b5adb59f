"""Finished-or-not for generated sets: each set is written into a hidden ``.<name>.partial`` folder whose
``synthetic.json`` marker (dataset, version, settings) is written last, then renamed into place, so a folder that
holds a marker is complete and an interrupted generation never looks finished."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

from fitting.files import fresh_partial, publish_folder
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.subjects import stand_in_notice

MARKER = "synthetic.json"


def is_finished(out: Path, dataset: str, config=None, version: int | None = None) -> bool:
    """True when ``out`` holds a finished ``dataset`` set (with these settings and version, if given)."""
    marker = Path(out) / MARKER
    try:
        written = json.loads(marker.read_text()) if marker.is_file() else None
    except (OSError, json.JSONDecodeError):
        return False
    if written is None or written.get("dataset") != dataset:
        return False
    return config is None or (written.get("config") == asdict(config) and written.get("version") == version)


def start_staging(out: Path, dataset: str, description: str) -> Path:
    """The empty staging folder for ``out``; refuses an ``out`` that holds anything but a finished set."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not is_finished(out, dataset):
        raise FileExistsError(f"{out}: exists and holds no finished {description}; choose another --out")
    partial = fresh_partial(out)
    return partial


def publish(partial: Path, out: Path, marker: dict) -> Path:
    """Write the marker last and move the staging folder into place (replacing an older finished set)."""
    (partial / MARKER).write_text(json.dumps(marker, indent=1))
    return publish_folder(partial, out)


def link_into(src: Path, dst: Path) -> None:
    """A file, or every file of a folder tree, at ``dst`` as hard links (copies where the file system refuses links):
    captures derived from another share its images without their disk space."""
    for path in [src] if src.is_file() else src.rglob("*"):
        target = dst / path.relative_to(src) if path != src else dst
        if path.is_dir():
            target.mkdir(parents=True, exist_ok=True)
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(path, target)
        except OSError:
            shutil.copy2(path, target)


def use_stand_in(out: Path, what: str, dataset: str, complete: Callable, make: Callable, quiet: bool, generate: bool):
    """The synthetic stand-in ``out`` used in place of a real ``what``: announced in one line on stderr (unless
    ``quiet``) and made by ``make()`` when ``complete(out)`` is False (``generate=False``: a CaptureError instead)."""
    if not quiet:
        state = "using" if complete(out) else "generating"
        stand_in_notice(f"no {what} given; {state} the synthetic stand-in at {out}")
    if not complete(out):
        if not generate:
            raise CaptureError(f"{out}: synthetic {what} not generated yet (run narf-synth --dataset {dataset})")
        make()
    return out
