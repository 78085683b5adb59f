"""Fit a run of any kind: ``fit(FitRequest) -> FitOutcome`` is what ``narf-fit`` and ``narf-experiments`` call, and
``start_run`` the one place a trainer is started or resumed (the kind's ``start``, ``pipelines.runs.kinds``)."""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Callable
from pathlib import Path

from fitting.checkpoint import load_checkpoint
from fitting.config import FitConfig, load_config
from fitting.distributed import SINGLE, Processes, barrier, from_environment, shutdown
from fitting.files import folder_lock
from fitting.fitted import run_config
from fitting.run_folder import auto_device, prepare_run_dir
from narf.fields import model_spec
from pipelines.body.locate import chosen_smpl_dir
from pipelines.runs.kinds import RUN_KINDS
from pipelines.runs.requests import FitInterrupted, FitOutcome, FitRequest

#: Settings that ``--resume`` may change (``--set``): how long to go on, how the learning rate ends, how often to
#: write.
RESUMABLE = (
    "train.checkpoint_minutes",
    "train.log_every",
    "train.lr_anneal",
    "train.lr_anneal_to",
    "train.steps",
    "train.validate_every",
)


def start_run(run_dir: Path, device, config: FitConfig, progress: bool = True, processes: Processes = SINGLE):
    """A new trainer of ``config`` in ``run_dir`` (its kind's ``start``)."""
    return _launch(config, run_dir, device, None, progress, processes)


def resume_run(
    run_dir: Path, device, overrides: list[str] | tuple[str, ...] = (), progress: bool = True, processes=SINGLE
):
    """The trainer of the checkpoint in ``run_dir``: its config (with ``overrides``, e.g. a longer ``train.steps``),
    weights and random state, so that it ends where an uninterrupted fit would."""
    state = load_checkpoint(run_dir, map_location=device)
    config = run_config(state, Path(run_dir), list(overrides))
    if config.train.steps < state["step"]:
        raise ValueError(
            f"{run_dir}: the run is at step {state['step']}; --set train.steps={config.train.steps} would end it "
            "before where it stands (give more steps, or leave train.steps as it is)"
        )
    return _launch(config, run_dir, device, state, progress, processes)


def _launch(config: FitConfig, run_dir: Path, device, state: dict | None, progress: bool, processes: Processes):
    """The one place a trainer is started or resumed: the kind's ``start``, data-parallel only where it may be."""
    kind = RUN_KINDS[config.kind]
    if processes.distributed and not kind.data_parallel:
        raise ValueError(f"data-parallel fitting (torchrun) covers subject runs; fit a {kind.name} run as one process")
    return kind.start(config, run_dir, device, state, progress, processes)


def request_config(request: FitRequest, gpu: bool) -> FitConfig | None:
    """The config of a new fit (the kind's default preset for the device and model unless ``request.preset``, then
    the request's fields and overrides); None when resuming, which keeps the saved one (only ``RESUMABLE`` keys may
    be set again)."""
    if request.resume:
        if request.out is None:
            raise ValueError("--resume needs --out (the run folder to continue)")
        changed = sorted({o.split("=", 1)[0].strip() for o in request.overrides} - set(RESUMABLE))
        fixed = (request.subject, request.data_root, request.model, request.kind, request.preset)
        if changed or any(fixed):
            raise ValueError(
                f"--resume continues the run as it was configured; only --set {', '.join(RESUMABLE)} may change (got "
                f"{', '.join(changed) or 'a preset, model, subject, kind or data root'})"
            )
        return None
    overrides = list(request.overrides)
    if request.data_root and not Path(request.data_root).is_dir():
        raise FileNotFoundError(f"{request.data_root}: no such data root folder")
    named = (("data.subject", request.subject), ("data.data_root", request.data_root), ("model.name", request.model))
    overrides[:0] = [f"{key}={value}" for key, value in named if value]
    if request.kind:
        overrides.insert(0, f"kind={request.kind}")
    kind = RUN_KINDS[request.kind or "subject"]
    return load_config(request.preset or kind.preset(request.model, gpu), overrides)


def default_out(config: FitConfig) -> Path:
    """``runs/<subject>-<model>`` for a subject run, ``runs/<kind>-<model>`` for the others."""
    name = Path(config.data.subject).name if config.kind == "subject" else config.kind
    return Path("runs") / f"{name}-{config.model.name}"


def fit(request: FitRequest, announce: Callable[[str], None] | None = None) -> FitOutcome:
    """Start (or resume) the requested fit and train until its steps or ``max_minutes`` are spent; ``announce``
    receives one line describing the fit before it trains. A Ctrl-C reaches the caller as KeyboardInterrupt after
    the trainer has saved its checkpoint. Under torchrun every process calls it. The request's ``smpl_dir`` is the
    body model of this fit only (``pipelines.body.locate.chosen_smpl_dir``)."""
    with chosen_smpl_dir(request.smpl_dir):
        return _fit(request, announce)


def _fit(request: FitRequest, announce: Callable[[str], None] | None) -> FitOutcome:
    import torch

    device = auto_device(request.device)
    processes = from_environment(device)
    if processes.distributed and device.type == "cuda":
        device = torch.device("cuda", processes.local_rank)
    config = request_config(request, device.type == "cuda")
    out = request.out or default_out(config)
    with folder_lock(out) if processes.is_main else contextlib.nullcontext():  # one writer per run folder
        return _fit_into(Path(out), request, config, device, processes, announce)


def _fit_into(out: Path, request: FitRequest, config: FitConfig, device, processes: Processes, announce) -> FitOutcome:
    import torch

    if request.resume and not (Path(out) / "checkpoint.pt").exists():
        raise FileNotFoundError(f"{out}: no checkpoint to resume")
    fresh = not request.resume and not Path(out).exists()
    run_dir = prepare_run_dir(out, request.resume, write=processes.is_main)
    barrier(processes)
    try:
        if request.resume:
            trainer = resume_run(run_dir, device, request.overrides, request.progress, processes)
        else:
            trainer = start_run(run_dir, device, config, request.progress, processes)
    except BaseException:  # bad data, Ctrl-C while loading: a fit that never started leaves no folder behind
        if fresh and processes.is_main:
            shutil.rmtree(run_dir, ignore_errors=True)
        raise
    if announce is not None and processes.is_main:
        c = trainer.config
        size = f"width {c.model.width}" if model_spec(c.model.name).rays else f"{c.model.image_size}^2"
        scale = f", {processes.world_size} processes" if processes.distributed else ""
        description = trainer.fit_data.description
        announce(f"{c.model.name} ({size}) on {description}, device {device}{scale}, torch {torch.__version__}")
    publish = RUN_KINDS[trainer.config.kind].publish if processes.is_main else None
    try:
        result = trainer.fit(request.max_minutes)
    except KeyboardInterrupt as interrupt:  # the trainer has saved a checkpoint on its way out
        if publish is not None:
            publish(run_dir)
        raise FitInterrupted(run_dir, trainer.step) from interrupt
    if publish is not None:
        publish(run_dir)
    shutdown(processes)
    return FitOutcome(run_dir, result.step, result.loss, result.psnr, result.finished, processes.is_main, result.kept)
