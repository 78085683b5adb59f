"""SMPL model files: reading official (chumpy) and plain pickles, validating them, writing plain pickles that
smplx loads without chumpy, and converting official files (``docs/formats.md``, SMPL model files).

Which file a run uses (the user's or the generated stand-in) is decided in ``pipelines.body.locate``.
"""

from __future__ import annotations

import io
import os
import pickle
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

import numpy as np
import scipy.sparse

from fitting.files import atomic_write_bytes
from pipelines.datasets.safe_pickle import ChumpyStub, RestrictedUnpickler

REQUIRED_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")
#: Module renames so that pickles written under numpy 2 / new scipy load under numpy 1.x / older scipy too.
_LEGACY_MODULES = {
    "numpy._core.multiarray": "numpy.core.multiarray",
    "numpy._core.numeric": "numpy.core.numeric",
    "numpy._core": "numpy.core",
    "scipy.sparse._csc": "scipy.sparse.csc",
}


class SmplFileError(ValueError):
    """An SMPL model file is missing, unreadable or malformed (the message names the file)."""


#: The cache folder chosen for the calls inside :func:`chosen_cache` (a benchmark's own), never written to the
#: environment, so that nothing outlives the block that chose it (as ``pipelines.body.locate``'s SMPL model).
_CHOSEN_CACHE: ContextVar[str | None] = ContextVar("narf_cache", default=None)


def cache_dir() -> Path:
    """Project cache folder: the one chosen for the current context (:func:`chosen_cache`), else ``$NARF_CACHE``,
    else ``~/.cache/narf-avatar``."""
    chosen = _CHOSEN_CACHE.get() or os.environ.get("NARF_CACHE")
    return Path(chosen) if chosen else Path.home() / ".cache" / "narf-avatar"


@contextmanager
def chosen_cache(path: str | Path) -> Iterator[None]:
    """``path`` is the cache folder of the calls inside the block (:func:`cache_dir`), and of the commands they
    start with :func:`command_environment`; no longer after it. A thread pool's workers do not inherit the choice:
    take the paths and environments they need before handing them work."""
    token = _CHOSEN_CACHE.set(str(path))
    try:
        yield
    finally:
        _CHOSEN_CACHE.reset(token)


def command_environment(**extra: str) -> dict[str, str]:
    """The environment of a command this process starts: its own, with ``NARF_CACHE`` set to :func:`cache_dir` (so
    that the command shares the cache chosen here) and the variables ``extra``."""
    return {**os.environ, "NARF_CACHE": str(cache_dir()), **extra}


class _LegacyPickler(pickle._Pickler):  # the pure-Python pickler lets us rename modules of globals
    def save_global(self, obj, name=None):
        module = getattr(obj, "__module__", None)
        if module in _LEGACY_MODULES:
            self.write(pickle.GLOBAL + f"{_LEGACY_MODULES[module]}\n{name or obj.__name__}\n".encode())
            self.memoize(obj)
            return
        super().save_global(obj, name)

    dispatch = dict(pickle._Pickler.dispatch)


def write_smpl_pickle(model: dict, path: Path) -> None:
    """Write an SMPL dict as a plain numpy/scipy pickle (protocol 2, numpy-1-loadable), atomically."""
    buffer = io.BytesIO()
    _LegacyPickler(buffer, protocol=2).dump(model)
    atomic_write_bytes(Path(path), buffer.getvalue())


def validate_smpl_dict(model: dict, source: str) -> None:
    """Check the keys and shapes smplx needs; raise :class:`SmplFileError` naming ``source``."""
    missing = [k for k in REQUIRED_KEYS if k not in model]
    if missing:
        raise SmplFileError(f"{source}: missing SMPL keys {missing}")
    n_verts = np.asarray(model["v_template"]).shape[0]
    checks = {
        "v_template": (n_verts, 3),
        "weights": (n_verts, 24),
        "J_regressor": (24, n_verts),
        "kintree_table": (2, 24),
    }
    for key, shape in checks.items():
        got = model[key].shape
        if tuple(got) != shape:
            raise SmplFileError(f"{source}: '{key}' has shape {tuple(got)}, expected {shape}")
    if n_verts != 6890:
        raise SmplFileError(f"{source}: {n_verts} vertices; smplx's SMPL needs 6890 (extra-joint vertex ids)")
    if np.asarray(model["shapedirs"]).shape[:2] != (n_verts, 3) or np.asarray(model["shapedirs"]).shape[2] < 10:
        raise SmplFileError(f"{source}: 'shapedirs' has shape {np.shape(model['shapedirs'])}, expected (6890,3,>=10)")
    for key in ("v_template", "weights", "J_regressor", "shapedirs", "posedirs"):
        try:
            value = model[key].data if scipy.sparse.issparse(model[key]) else model[key]  # J_regressor: sparse
            values = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise SmplFileError(f"{source}: '{key}' is not numeric") from None
        if not np.isfinite(values).all():
            raise SmplFileError(f"{source}: '{key}' contains NaN or infinite values")
    faces = np.asarray(model["f"])
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
        raise SmplFileError(f"{source}: 'f' has shape {faces.shape} ({faces.dtype}), expected (F, 3) vertex indices")
    if faces.size and (faces.min() < 0 or faces.max() >= n_verts):
        worst = faces.max() if faces.max() >= n_verts else faces.min()
        raise SmplFileError(f"{source}: 'f' indexes vertex {worst}, outside 0..{n_verts - 1}")
    parents = np.asarray(model["kintree_table"])[0, 1:]
    if parents.dtype.kind not in "iu" or (parents < 0).any() or (parents >= 24).any():
        raise SmplFileError(f"{source}: 'kintree_table' has parents outside 0..23")


def _unwrap(value):
    if isinstance(value, ChumpyStub):
        if "x" not in value.__dict__:
            raise SmplFileError(f"a chumpy object without an array 'x' (has {sorted(value.__dict__)})")
        return np.asarray(value.__dict__["x"])
    return value


def load_smpl_dict(path: Path) -> dict:
    """Read an SMPL pickle (official chumpy-based or plain) into a plain dict of numpy/scipy objects."""
    path = Path(path)
    if not path.is_file():
        raise SmplFileError(f"{path}: no such SMPL model file")
    try:
        with open(path, "rb") as handle:
            raw = RestrictedUnpickler(handle, chumpy=True, encoding="latin1").load()
    except (pickle.UnpicklingError, EOFError, ModuleNotFoundError, AttributeError) as err:
        raise SmplFileError(f"{path}: not a readable SMPL pickle ({err})") from err
    if not isinstance(raw, dict):
        raise SmplFileError(f"{path}: expected a pickled dict, got {type(raw).__name__}")
    model = {key: _unwrap(value) for key, value in raw.items()}
    validate_smpl_dict(model, str(path))
    return model


def convert_official_pickle(src: Path, dst: Path) -> Path:
    """Convert an official (chumpy) SMPL pickle to a plain one that smplx loads without chumpy."""
    model = load_smpl_dict(src)
    if not scipy.sparse.issparse(model["J_regressor"]):
        model["J_regressor"] = scipy.sparse.csc_matrix(model["J_regressor"])
    model["f"] = np.asarray(model["f"]).astype(np.uint32)
    write_smpl_pickle(model, Path(dst))
    return Path(dst)
