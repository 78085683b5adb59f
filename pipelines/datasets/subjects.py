"""Subjects by name: real ZJU-MoCap data under the data root, else the synthetic capture (generated on demand).

``--subject taichi`` looks for ``CoreView_315`` under ``$NARF_DATA`` (default ``data/``), in ``<root>``,
``<root>/zju_mocap`` and ``<root>/ZJU-MoCap``; without it, it falls back to ``<root>/synthetic/taichi`` and says
so in one line. A path to a folder holding ``annots.npy`` is used as it is.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from pipelines.zju_mocap import CaptureError

#: ZJU-MoCap action names -> subject ids (data-formats.md §1.1).
ZJU_SUBJECTS = {"twirl": 313, "taichi": 315, "warmup": 377, "punch1": 386, "punch2": 387, "kick": 390,
                "swing1": 392, "swing3": 393, "swing2": 394}  # fmt: skip
#: Subjects the synthetic generator can stand in for.
SYNTHETIC_SUBJECTS = ("taichi",)


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


def resolve_subject(name: str, root: str | Path | None = None, generate: bool = True, quiet: bool = False) -> Path:
    """Folder of subject ``name`` (module docstring); generates the synthetic stand-in when needed.

    Raises:
        CaptureError: no real data and no synthetic stand-in for this name.
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
    key = name.lower()
    if key not in SYNTHETIC_SUBJECTS:
        looked = ", ".join(str(p) for p in real_candidates(name, root)[:3])
        raise CaptureError(f"no subject '{name}' under {root} (looked in {looked}, ...); synthetic stand-ins exist "
                           f"for: {', '.join(SYNTHETIC_SUBJECTS)}")  # fmt: skip
    from pipelines.synthetic import SynthConfig, generate_capture, is_complete

    out = synthetic_path(key, root)
    if not quiet:
        state = "using" if is_complete(out) else "generating"
        print(f"narf: no real '{name}' capture under {root}; {state} the synthetic stand-in at {out}", file=sys.stderr)
    if not is_complete(out):
        if not generate:
            raise CaptureError(f"{out}: synthetic capture not generated yet (run narf-synth --subject {key})")
        generate_capture(out, SynthConfig(subject=key))
    return out
