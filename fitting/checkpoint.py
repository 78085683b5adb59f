"""Checkpoints: atomic writes, and loads that fail with a clear message on a missing or corrupt file."""

from __future__ import annotations

import io
from pathlib import Path

import torch

from fitting.files import atomic_write_bytes, remove_stale

CHECKPOINT_NAME = "checkpoint.pt"
FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint is missing, corrupt or of another format (the message names the file)."""


def save_checkpoint(run_dir: Path, state: dict) -> Path:
    """Write ``run_dir/checkpoint.pt`` atomically (temporary file, fsync, rename); a kill mid-write leaves the
    previous checkpoint intact and a hidden temporary file, removed by the next save."""
    run_dir = Path(run_dir)
    path = run_dir / CHECKPOINT_NAME
    remove_stale(path)
    buffer = io.BytesIO()
    torch.save({"format": FORMAT_VERSION, **state}, buffer)
    atomic_write_bytes(path, buffer.getvalue(), sync=True)
    return path


def _reason(err: Exception) -> str:
    """Why torch could not read a file, in one line. torch's weights-only message opens with advice to load the file
    the unsafe way; only its reason (an unsupported global, a bad opcode) is kept."""
    text = str(err).strip()
    if not text.lower().startswith("weights only load failed"):
        return f"{type(err).__name__}: {text.splitlines()[0] if text else ''}"
    noise = ("weights only load failed", "check the documentation", "please file an issue")
    lines = [line.strip() for line in text.splitlines() if line.strip() and not line.strip().lower().startswith(noise)]
    reason = " ".join(lines).replace("WeightsUnpickler error:", "").strip()
    if "global" in reason.lower():
        return f"it holds objects other than tensors and plain values ({reason}); refused, loading it could run code"
    return f"not a tensor file: {reason or 'unreadable pickle'}"


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
        raise CheckpointError(f"{path}: corrupt or unreadable checkpoint ({_reason(err)})") from err
    if not isinstance(state, dict) or state.get("format") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: not a narf-avatar checkpoint of format {FORMAT_VERSION}")
    for key in ("config", "step", "model"):
        if key not in state:
            raise CheckpointError(f"{path}: checkpoint lacks '{key}'")
    step = state["step"]
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise CheckpointError(f"{path}: 'step' must be a whole number >= 0, got {step!r}")
    for key in ("config", "model"):
        if not isinstance(state[key], dict):
            raise CheckpointError(f"{path}: '{key}' must be a mapping, got {type(state[key]).__name__}")
    return state
