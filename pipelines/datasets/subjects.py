"""Subjects by name: where the real ZJU-MoCap capture of a subject lives under the data root.

``--subject taichi`` looks for ``CoreView_315`` under ``$NARF_DATA`` (default ``data/``), in ``<root>``,
``<root>/zju_mocap`` and ``<root>/ZJU-MoCap``. A path to a folder holding ``annots.npy`` is used as it is.
The fallback to the synthetic stand-in (``<root>/synthetic/<name>``) is decided by the glue that opens a
subject for fitting (``pipelines.runs.subject.session.resolve_subject``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from pipelines.datasets.errors import CaptureError

#: ZJU-MoCap action names -> subject ids (docs/formats.md, ZJU-MoCap).
ZJU_SUBJECTS = {
    "twirl": 313,
    "taichi": 315,
    "warmup": 377,
    "punch1": 386,
    "punch2": 387,
    "kick": 390,
    "swing1": 392,
    "swing3": 393,
    "swing2": 394,
}


def stand_in_notice(text: str) -> None:
    """Say on stderr, in one line, that a generated stand-in takes the place of real data (``text``: what and
    where). Every stand-in (body model, captures, THUman, SURREAL, the rigid set) is announced through here."""
    print(f"narf: {text}", file=sys.stderr)


def data_root(explicit: str | Path | None = None) -> Path:
    """The data root: an explicit ``--data-root``, else ``$NARF_DATA``, else ``data/``."""
    return Path(explicit or os.environ.get("NARF_DATA", "data"))


def _subject_id(name: str) -> int | None:
    key = name.lower().removeprefix("coreview_")
    if key.isdigit():
        return int(key)
    return ZJU_SUBJECTS.get(key)


def real_candidates(name: str, root: Path) -> list[Path]:
    """Folders where real data of subject ``name`` may live."""
    subject_id = _subject_id(name)
    folders = [f"CoreView_{subject_id}"] if subject_id else []
    folders.append(name)
    return [base / folder for base in (root, root / "zju_mocap", root / "ZJU-MoCap") for folder in folders]


def synthetic_path(name: str, root: Path) -> Path:
    return root / "synthetic" / name


def find_subject(name: str, root: str | Path | None = None) -> Path | None:
    """Folder of the real capture of subject ``name`` (module docstring), or None when there is none.

    Raises:
        CaptureError: the data root is a file.
    """
    as_path = Path(name)
    if (as_path / "annots.npy").is_file():
        return as_path
    root = data_root(root)
    if root.exists() and not root.is_dir():
        raise CaptureError(f"{root}: the data root is a file, not a folder")
    for candidate in real_candidates(name, root):
        if (candidate / "annots.npy").is_file():
            return candidate
    return None
