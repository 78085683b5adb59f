"""A run folder's checkpoint as a config and a model: the one path from ``checkpoint.pt`` to weights ready to render
(evaluation, videos, meshes, experiments) or to train on (``--resume``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from fitting.checkpoint import CheckpointError, load_checkpoint
from fitting.config import ConfigError, FitConfig, load_config, migrate_saved
from fitting.model_setup import make_field
from fitting.selection import kept_weights


def run_config(state: dict, path: Path, overrides: list[str] | None = None) -> FitConfig:
    """The config a checkpoint was fitted with (older keys migrated, ``fitting.config.migrate_saved``), with
    ``overrides`` applied; a config that is not one names the file."""
    try:
        return load_config(base=migrate_saved(state["config"], state.get("kind")), overrides=overrides)
    except ConfigError as err:
        raise CheckpointError(f"{path}: {err}") from err


@dataclass(frozen=True)
class SavedRun:
    """A run folder with its checkpoint read once (on the CPU): the ``state`` and the ``config`` it was fitted with.
    Commands read it once and hand it on; every loader below also takes the folder itself."""

    run_dir: Path
    state: dict
    config: FitConfig


def run_folder(run: Path | SavedRun) -> Path:
    """The folder of ``run`` (a folder, or its checkpoint already read)."""
    return run.run_dir if isinstance(run, SavedRun) else Path(run)


def read_run(run: Path | SavedRun) -> SavedRun:
    """``run`` as a :class:`SavedRun`: its checkpoint read and its config checked, unless it is one already."""
    if isinstance(run, SavedRun):
        return run
    state = load_checkpoint(Path(run))
    return SavedRun(Path(run), state, run_config(state, Path(run)))


@dataclass
class Fitted:
    """A fitted run: its checkpoint ``state``, ``config`` and the ``field`` (eval mode) on the device, with the
    weights of step ``kept_step`` (``fitting.selection.kept_weights``: the last step unless frames were held back)."""

    state: dict
    config: FitConfig
    field: torch.nn.Module
    kept_step: int | None = None

    @property
    def step(self) -> int:
        return int(self.state["step"])


def load_weights(module: torch.nn.Module, weights: dict, path: Path, what: str) -> None:
    """``module.load_state_dict(weights)``; weights of another model or size fail with the file and the reason."""
    try:
        module.load_state_dict(weights)
    except (RuntimeError, TypeError, AttributeError) as err:
        first = str(err).strip().splitlines()
        detail = first[1].strip() if len(first) > 1 else (first[0] if first else type(err).__name__)
        raise CheckpointError(f"{path}: its weights do not fit {what} ({detail})") from err


def load_fitted(run: Path | SavedRun, device="cpu", kind: str | None = None) -> Fitted:
    """Build the model of a run folder's checkpoint on ``device`` (``run``: the folder, or its checkpoint already
    read); ``kind`` refuses a run of another kind first."""
    saved = read_run(run)
    run_dir, state, config = saved.run_dir, saved.state, saved.config
    if kind is not None and config.kind != kind:
        raise CheckpointError(f"{run_dir}: holds a {config.kind} run; this needs a {kind} run")
    weights, step = kept_weights(state, config.train.keep)  # the step chosen on held-back frames, or the last
    field = make_field(config, step).to(device)
    load_weights(field, weights, run_dir, f"the {config.model.name} model of its config")
    bad = next((name for name, value in field.state_dict().items() if not torch.isfinite(value).all()), None)
    if bad is not None:
        raise CheckpointError(f"{run_dir}: its weights are not finite ({bad}); nothing to render from a diverged fit")
    return Fitted(state, config, field.eval(), step)
