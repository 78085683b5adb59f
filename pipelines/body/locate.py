"""Which SMPL model file a run uses: an explicit file or folder, then the command's ``--smpl-dir``, then
``$NARF_SMPL_DIR``, then the generated
stand-in in the cache (``$NARF_CACHE`` or ``~/.cache/narf-avatar``), generated once on first use.
"""

from __future__ import annotations

import functools
import hashlib
import os
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

from pipelines.body.standin import build_standin_model
from pipelines.datasets.smpl_files import SmplFileError, cache_dir, write_smpl_pickle
from pipelines.datasets.subjects import stand_in_notice


def standin_path() -> Path:
    """Path of the generated stand-in ``SMPL_NEUTRAL.pkl`` inside the cache (smplx ``create`` layout)."""
    return cache_dir() / "body_models" / "smpl" / "SMPL_NEUTRAL.pkl"


def ensure_standin(path: Path | None = None) -> Path:
    """Generate the stand-in body model once (atomically) and return its path."""
    path = Path(path) if path else standin_path()
    if not path.is_file():
        stand_in_notice(f"generating the stand-in SMPL body model at {path}")
        write_smpl_pickle(build_standin_model(), path)
    return path


#: The SMPL model file or folder a command or request was given (``--smpl-dir``), for the calls it makes: set inside
#: :func:`chosen_smpl_dir`'s scope (or a CLI's own context, ``pipelines.cli.common.run_cli``), never in the
#: environment, so that nothing outlives the command that chose it.
_CHOSEN_SMPL: ContextVar[str | None] = ContextVar("narf_smpl_dir", default=None)


def default_smpl_dir() -> str | None:
    """The SMPL model of calls that name none: the command's ``--smpl-dir`` (:func:`chosen_smpl_dir`), else
    ``$NARF_SMPL_DIR``, else None (the stand-in)."""
    return _CHOSEN_SMPL.get() or os.environ.get("NARF_SMPL_DIR") or None


def choose_smpl_dir(path: str | Path | None) -> None:
    """Make ``path`` (when given) the default SMPL model of the current context: a CLI's ``--smpl-dir``, whose
    ``main`` runs in a context of its own. Library code uses :func:`chosen_smpl_dir` instead."""
    if path:
        _CHOSEN_SMPL.set(str(path))


@contextmanager
def chosen_smpl_dir(path: str | Path | None) -> Iterator[None]:
    """``path`` (when given) is the default SMPL model of the calls inside the block, and no longer after it."""
    token = _CHOSEN_SMPL.set(str(path)) if path else None
    try:
        yield
    finally:
        if token is not None:
            _CHOSEN_SMPL.reset(token)


def resolve_smpl_file(smpl_dir: str | Path | None = None, gender: str = "neutral") -> Path:
    """Find the SMPL model: explicit path/dir, then the command's choice or ``$NARF_SMPL_DIR``
    (:func:`default_smpl_dir`), then the generated stand-in."""
    for candidate in (smpl_dir, default_smpl_dir()):
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


#: What a run or a capture records of the body model its poses belong to (docs/formats.md §1.11).
BODY_MODEL_RECORD = "body_model.json"


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, in hex; read once per file version (path, size, modification time), since a
    fit or a command checks the same body model several times."""
    stat = Path(path).stat()
    return _sha256(str(Path(path).resolve()), stat.st_size, stat.st_mtime_ns)


@functools.lru_cache(maxsize=16)
def _sha256(path: str, size: int, mtime_ns: int) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def body_model_record(path: Path) -> dict:
    """``{"file", "sha256", "standin"}`` of the body model file ``path`` (``standin``: the generated stand-in)."""
    path = Path(path).resolve()
    return {"file": str(path), "sha256": file_sha256(path), "standin": path == standin_path().resolve()}


def check_record(record, source: str) -> dict:
    """A body-model record read from ``source`` (a file or checkpoint), checked: a mapping with a file name, a
    64-digit hex SHA-256 and a true/false stand-in flag."""
    ok = (
        isinstance(record, dict)
        and isinstance(record.get("file"), str)
        and isinstance(record.get("sha256"), str)
        and len(record["sha256"]) == 64
        and all(c in "0123456789abcdef" for c in record["sha256"])
        and isinstance(record.get("standin"), bool)
    )
    if not ok:
        raise SmplFileError(f"{source}: not a body-model record (expected file, a 64-digit sha256 and standin)")
    return record


def recorded_body_file(state: dict, source: str, owner: str) -> Path | None:
    """The body model file a checkpoint ``state`` (read from ``source``) records (:func:`find_recorded`), or None for a
    checkpoint written before runs recorded one."""
    record = (state.get("provenance") or {}).get("body_model")
    return None if record is None else find_recorded(check_record(record, source), owner)


def find_recorded(record: dict, owner: str) -> Path:
    """The body model file with the recorded hash: the recorded file, then the command's ``--smpl-dir`` or
    ``$NARF_SMPL_DIR`` (:func:`default_smpl_dir`), then the stand-in when the record names the stand-in. ``owner``
    names the run or capture in the error.

    Raises:
        SmplFileError: no candidate has the recorded hash.
    """
    candidates = [Path(record["file"])]
    if default_smpl_dir():
        try:
            candidates.append(resolve_smpl_file(default_smpl_dir()))
        except SmplFileError:
            pass
    if record["standin"]:
        candidates.append(ensure_standin())
    for candidate in dict.fromkeys(candidates):
        if candidate.is_file() and file_sha256(candidate) == record["sha256"]:
            return candidate
    what = "the generated stand-in body" if record["standin"] else f"the body model {record['file']}"
    raise SmplFileError(
        f"{owner}: was made with {what} (sha256 {record['sha256'][:12]}...), which is not found or has changed; "
        "pass --smpl-dir with that file"
    )
