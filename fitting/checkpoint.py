"""Checkpoints: atomic writes, and loads that fail with a clear message on a missing or corrupt file."""

from __future__ import annotations

import io
import os
import tempfile
from pathlib import Path

import torch

CHECKPOINT_NAME = "checkpoint.pt"
FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint is missing, corrupt or of another format (the message names the file)."""


def save_checkpoint(run_dir: Path, state: dict) -> Path:
    """Write ``run_dir/checkpoint.pt`` atomically (temporary file, fsync, rename); a kill mid-write leaves the
    previous checkpoint intact and a hidden temporary file, removed by the next save."""
    run_dir = Path(run_dir)
    path = run_dir / CHECKPOINT_NAME
    for stale in run_dir.glob(".checkpoint.*.tmp"):  # left by a writer killed mid-write (one writer per run)
        stale.unlink(missing_ok=True)
    buffer = io.BytesIO()
    torch.save({"format": FORMAT_VERSION, **state}, buffer)
    fd, tmp = tempfile.mkstemp(dir=run_dir, prefix=".checkpoint.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(buffer.getvalue())
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(run_dir: Path, map_location="cpu") -> dict:
    """Read ``run_dir/checkpoint.pt`` (or a checkpoint file path)."""
    path = Path(run_dir)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint (is this a run folder written by narf-fit --out?)")
    try:
        # weights_only: tensors and plain Python values only, so a crafted checkpoint cannot run code
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # torch raises many kinds on truncated or foreign files
        raise CheckpointError(f"{path}: corrupt or unreadable checkpoint ({type(err).__name__}: {err})") from err
    if not isinstance(state, dict) or state.get("format") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: not a narf-avatar checkpoint of format {FORMAT_VERSION}")
    for key in ("config", "step", "model"):
        if key not in state:
            raise CheckpointError(f"{path}: checkpoint lacks '{key}'")
    return state
