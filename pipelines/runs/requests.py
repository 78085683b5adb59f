"""What a caller asks of a run, as plain values: a fit, an evaluation, a video. The commands build these from their
flags; ``narf-experiments`` and library users build them directly (no argv, no exit codes)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class FitRequest:
    """A fit to start, or (``resume``) to continue in ``out``.

    ``preset``: a preset name or YAML file; None takes the kind's default for the device and model
    (``pipelines.runs.kinds.RunKind.preset``). ``kind``, ``model``, ``subject`` and ``data_root`` override the
    preset, then ``overrides`` (``section.key=value``). ``out`` None: ``runs/<subject or kind>-<model>``.
    ``smpl_dir``: the SMPL model folder or file of this fit (default: ``$NARF_SMPL_DIR``, else the stand-in).
    """

    out: Path | None = None
    preset: str | None = None
    kind: str | None = None
    model: str | None = None
    subject: str | None = None
    data_root: str | None = None
    overrides: tuple[str, ...] = ()
    resume: bool = False
    max_minutes: float | None = None
    device: str = "auto"
    progress: bool = True
    smpl_dir: str | None = None


class FitInterrupted(KeyboardInterrupt):
    """Ctrl-C during a fit, after the trainer saved its checkpoint: ``run_dir`` and the ``step`` it stopped at."""

    def __init__(self, run_dir: Path, step: int):
        super().__init__(f"interrupted at step {step}")
        self.run_dir, self.step = run_dir, step


@dataclass(frozen=True)
class FitOutcome:
    """Where a fit stopped: its run folder, step, last training loss and PSNR, whether it reached its steps, and
    whether this process is the one that writes (rank 0 of a data-parallel fit, or the only one)."""

    run_dir: Path
    step: int
    loss: float
    psnr: float
    finished: bool
    main_process: bool = True
    kept: tuple[int, float] | None = None  #: (step, held-back frames' PSNR) of the weights kept (fitting.selection)


@dataclass(frozen=True)
class EvalRequest:
    """An evaluation: ``splits`` (already expanded), at most ``limit`` views per split, ``grids`` image grids per
    split; per-subject runs: ``mesh`` (surface distance, at ``mesh_resolution`` / ``mesh_level``) and ``capture``
    (another recording of the person, split ``capture``); autoencoder runs: ``surreal`` (cross_dataset set) and
    ``refine_steps``; ``novel_colour`` (subject runs) the colour of frames the fit did not train on, and
    ``samples`` (subject runs) the renders' coarse and importance samples a ray, each in place of the run's setting."""

    splits: tuple[str, ...]
    limit: int | None = None
    device: str = "cpu"
    progress: bool = True
    grids: int = 4
    mesh: bool = False
    mesh_resolution: int = 256
    mesh_level: float | None = None
    surreal: str | None = None
    refine_steps: int = 0
    capture: Path | None = None
    novel_colour: str | None = None  #: subject runs: ``model.novel_colour`` for this evaluation (None: the run's)
    samples: tuple[int, int] | None = None  #: subject runs: ``render.eval_coarse`` / ``eval_fine`` (None: the run's)
    frame_step: int | None = None  #: subject runs: every Nth frame of a split's range (None: the protocol's interval)


@dataclass(frozen=True)
class VideoRequest:
    """A video of ``kind`` into ``out``: ``frames`` at ``fps``. Per-subject runs: ``motion`` (from ``start``, at
    ``motion_fps`` when the file has no rate), ``camera``, bone ``scale``, ``samples`` (the renders' coarse and
    importance samples a ray in place of the run's); autoencoder runs: ``inputs`` (people to encode) and
    ``refine_steps``."""

    kind: str
    out: Path
    frames: int = 60
    fps: int = 24
    device: str = "cpu"
    progress: bool = True
    inputs: tuple[str, ...] = field(default=())
    refine_steps: int = 0
    motion: Path | None = None
    camera: int | None = None
    scale: float = 1.3
    start: int = 0
    motion_fps: float | None = None
    camera_path: Path | None = None
    samples: tuple[int, int] | None = None  #: subject runs: ``render.eval_coarse`` / ``eval_fine`` (None: the run's)


@dataclass(frozen=True)
class MotionClip:
    """Part of a motion file to play: ``path`` (an AMASS .npz, a ZJU-MoCap params folder or a SURREAL _info.mat)
    from source frame ``start`` for at most ``frames`` (None: to the end), resampled to ``fps`` (None: the motion's
    own rate); ``source_fps``: the file's rate when it records none; ``flag``: the option that gave ``start``, named
    when it lies outside the motion."""

    path: Path
    start: int = 0
    frames: int | None = None
    fps: float | None = None
    source_fps: float | None = None
    flag: str = "--start"


@dataclass(frozen=True)
class ExportRequest:
    """A mesh export into ``out``: the body at capture ``frame``, or at frames ``window = (A, B)`` (B excluded) of a
    ``motion`` file, extracted at ``resolution`` and density ``level`` (None: chosen from the fit). The rigged export
    (``rigged``): ``frame`` None is the rest pose, a ``motion`` becomes its animation at ``fps`` (``motion_fps``: the
    file's rate when it records none), ``skin`` the skinning rule."""

    out: Path
    frame: int | None = None
    motion: Path | None = None
    window: tuple[int, int] | None = None
    resolution: int = 256
    level: float | None = None
    rigged: bool = False
    skin: str = "selector"
    fps: float | None = None
    motion_fps: float | None = None
    device: str = "cpu"
    progress: bool = True


def a_run(kind: str) -> str:
    """'a subject run', 'an autoencoder run', 'a rigid run': the kind in a message."""
    return f"{'an' if kind[0] in 'aeiou' else 'a'} {kind} run"


def refuse_options(run_dir: Path, kind: str, options: dict[str, object], users: str) -> None:
    """Options a run kind does not read are refused, never ignored: ``options`` maps a flag name to its value."""
    given = [name for name, value in options.items() if value]
    if given:
        verb = "is" if len(given) == 1 else "are"
        raise ValueError(f"{run_dir}: {a_run(kind)}; {', '.join(given)} {verb} for {users}")
