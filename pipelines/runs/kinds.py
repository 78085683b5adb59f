"""The run kinds, one table: what each kind of run fits, its default presets, and how it starts or resumes,
evaluates, renders and exports. Commands and experiments look a run's kind up here (``config.kind``) instead of
branching on it; docs/guides/fitting.md describes the kinds."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from fitting.config import FitConfig
from fitting.distributed import Processes
from fitting.evaluate import ALL_SPLITS, EVAL_SPLITS
from fitting.fitted import SavedRun, read_run
from fitting.trainer import Trainer
from narf.fields import MODEL_SPECS
from pipelines.runs.autoencoder import evaluation as autoencoder_evaluation
from pipelines.runs.autoencoder import session as autoencoder_session
from pipelines.runs.autoencoder import video as autoencoder_video
from pipelines.runs.requests import EvalRequest, ExportRequest, VideoRequest, a_run
from pipelines.runs.rigid import session as rigid_session
from pipelines.runs.subject import evaluation as subject_evaluation
from pipelines.runs.subject import mesh as subject_mesh
from pipelines.runs.subject import rigged as subject_rigged
from pipelines.runs.subject import session as subject_session
from pipelines.runs.subject import video as subject_video

#: A run as the entries take it: its folder, or its checkpoint already read (``fitting.fitted.read_run``).
Run = Path | SavedRun


class Start(Protocol):
    """Starts a fit of the kind, or resumes one (``state``: the checkpoint it resumes; ``processes``: this process's
    place in a data-parallel fit)."""

    def __call__(
        self, config: FitConfig, run_dir: Path, device, state: dict | None, progress: bool, processes: Processes
    ) -> Trainer: ...


@dataclass(frozen=True)
class RunKind:
    """One kind of run.

    Attributes:
        name: the kind's one name (``config.kind``, ``narf-fit --kind``).
        presets: default preset (CPU, CUDA); ``image_presets`` the same for an image model (``--model cnn``).
        data: finds (or generates) the data of a config; returns its folder.
        start: starts or resumes a fit (:class:`Start`).
        data_parallel: whether torchrun may split its fit over processes.
        splits: the splits ``narf-eval`` accepts; ``default_split`` the one without ``--split``; ``every``: what
            ``all`` stands for.
        evaluate: ``(run, EvalRequest) -> report``; ``markdown``: ``report -> table``.
        videos: the ``narf-render-video --kind`` values; ``render``: ``(run, VideoRequest) -> mp4 path``.
        export: ``narf-export-mesh``'s work, ``(run, ExportRequest) -> (files, level record)``, or None where the kind
            has no mesh export; ``rigged``: its ``--rigged``, ``(run, ExportRequest) -> (glb, record)``.
        publish: ``run_dir -> ...``, run after every fit (finished or stopped): writes what the checkpoint holds for
            other tools (a subject run's corrected poses), or None.
    """

    name: str
    presets: tuple[str, str]
    image_presets: tuple[str, str] | None
    data: Callable[[FitConfig], Path]
    start: Start
    data_parallel: bool
    splits: tuple[str, ...]
    default_split: str
    every: tuple[str, ...]
    evaluate: Callable[[Run, EvalRequest], dict]
    markdown: Callable[[dict], str]
    videos: tuple[str, ...] = ()
    render: Callable[[Run, VideoRequest], Path] | None = None
    export: Callable[[Run, ExportRequest], tuple[list[Path], dict]] | None = None
    rigged: Callable[[Run, ExportRequest], tuple[Path, dict]] | None = None
    publish: Callable[[Path], object] | None = None

    def preset(self, model: str | None, gpu: bool) -> str:
        """The default preset for ``model`` on this device."""
        image = model in MODEL_SPECS and MODEL_SPECS[model].family == "image"
        presets = self.image_presets if image and self.image_presets else self.presets
        return presets[gpu]

    def expand(self, run_dir: Path, requested: list[str] | None) -> tuple[str, ...]:
        """The splits to evaluate (default: ``default_split``): ``all`` stands for ``every``; each split once, in the
        order first named. A split of another kind is an error naming the run."""
        requested = requested or [self.default_split]
        for split in requested:
            if split != "all" and split not in self.splits:
                choices = ", ".join((*self.splits, "all"))
                raise ValueError(f"{run_dir}: {a_run(self.name)}; '{split}' is not one of its splits ({choices})")
        return tuple(dict.fromkeys(n for split in requested for n in (self.every if split == "all" else (split,))))


def _subject_data(config: FitConfig) -> Path:
    return subject_session.resolve_subject(config.data.subject, config.data.data_root)


RUN_KINDS: dict[str, RunKind] = {
    "subject": RunKind(
        name="subject",
        presets=("cpu", "paper"),
        image_presets=("cnn", "cnn"),
        data=_subject_data,
        start=subject_session.start,
        data_parallel=True,
        splits=tuple(s for s in ALL_SPLITS if s != "all"),
        default_split="novel_pose",
        every=EVAL_SPLITS,
        evaluate=subject_evaluation.evaluate_run,
        markdown=subject_evaluation.markdown_table,
        videos=subject_video.VIDEO_KINDS,
        render=subject_video.render_video,
        export=subject_mesh.export_run_meshes,
        rigged=subject_rigged.export_rigged,
        publish=subject_session.write_refined_params,
    ),
    "autoencoder": RunKind(
        name="autoencoder",
        presets=("ae_cpu", "ae_paper"),
        image_presets=("ae_cnn", "ae_cnn_paper"),
        data=autoencoder_session.resolve_thuman,
        start=autoencoder_session.start,
        data_parallel=False,
        splits=autoencoder_evaluation.AUTOENCODER_SPLITS,
        default_split="novel_pose_novel_view",
        every=autoencoder_evaluation.AUTOENCODER_SPLITS,
        evaluate=autoencoder_evaluation.evaluate_autoencoder_run,
        markdown=autoencoder_evaluation.markdown_autoencoder,
        videos=autoencoder_video.AUTOENCODER_VIDEO_KINDS,
        render=autoencoder_video.render_autoencoder_video,
    ),
    "rigid": RunKind(
        name="rigid",
        presets=("rigid_cpu", "rigid_paper"),
        image_presets=None,
        data=rigid_session.resolve_rigid,
        start=rigid_session.start,
        data_parallel=False,
        splits=("test",),
        default_split="test",
        every=("test",),
        evaluate=rigid_session.evaluate_rigid_run,
        markdown=rigid_session.markdown_rigid,
    ),
}


def open_run(run_dir: Path) -> tuple[RunKind, SavedRun]:
    """The run in ``run_dir``, its checkpoint read once (:func:`fitting.fitted.read_run`; older runs' keys migrated),
    and its kind. The commands hand the :class:`SavedRun` on to the kind's entries."""
    saved = read_run(Path(run_dir))
    return RUN_KINDS[saved.config.kind], saved
