"""Which SMPL model file a run uses: an explicit ``--smpl-dir`` / file, then ``$NARF_SMPL_DIR``, then the generated
stand-in in the cache (``$NARF_CACHE`` or ``~/.cache/narf-avatar``), generated once on first use.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from pipelines.body.standin import build_standin_model
from pipelines.datasets.smpl_files import SmplFileError, cache_dir, write_smpl_pickle


def standin_path() -> Path:
    """Path of the generated stand-in ``SMPL_NEUTRAL.pkl`` inside the cache (smplx ``create`` layout)."""
    return cache_dir() / "body_models" / "smpl" / "SMPL_NEUTRAL.pkl"


def ensure_standin(path: Path | None = None) -> Path:
    """Generate the stand-in body model once (atomically) and return its path."""
    path = Path(path) if path else standin_path()
    if not path.is_file():
        print(f"narf: generating the stand-in SMPL body model at {path}", file=sys.stderr)
        write_smpl_pickle(build_standin_model(), path)
    return path


def resolve_smpl_file(smpl_dir: str | Path | None = None, gender: str = "neutral") -> Path:
    """Find the SMPL model: explicit path/dir, then ``$NARF_SMPL_DIR``, then the generated stand-in."""
    for candidate in (smpl_dir, os.environ.get("NARF_SMPL_DIR")):
        if not candidate:
            continue
        candidate = Path(candidate)
        if candidate.is_file():
            return candidate
        short = {"female": "f", "male": "m"}.get(gender.lower(), gender.lower())
        names = [
            f"SMPL_{gender.upper()}.pkl",
            f"smpl/SMPL_{gender.upper()}.pkl",
            f"basicmodel_{short}_lbs_10_207_0_v1.0.0.pkl",
            f"basicmodel_{short}_lbs_10_207_0_v1.1.0.pkl",
        ]
        present = {p.name.lower(): p for p in candidate.glob("*.pkl")} if candidate.is_dir() else {}
        for name in names:
            if (candidate / name).is_file():
                return candidate / name
            if name.lower() in present:
                return present[name.lower()]
        raise SmplFileError(f"{candidate}: no SMPL model file for gender '{gender}' (looked for {names})")
    return ensure_standin()
