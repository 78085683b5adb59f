"""The pose correction's controlled check (docs/guides/fitting.md, *Pose correction*): a field fitted on exact poses,
held fixed, while only the poses of a capture whose bodies were broken (``narf-synth --degrade``) are corrected. The
joint error against the truth, measured along the way, says whether the photometric signal reaches the poses and
where the correction goes; with the field fixed the truth is the loss's minimum, so anything short of it is the
correction's own fault.

``correct_with_field_fixed(PoseCheckRequest(field_run, capture, truth, steps))`` returns the path of the joint error
over the steps."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from fitting.config import TrainConfig
from fitting.fitted import read_run, run_config
from pipelines.body.model import BodyModel
from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.zju_mocap import SmplParams
from pipelines.runs.subject.body_refine import RefinedCapture, corrected_frames
from pipelines.synthetic.degrade import joint_errors


@dataclass
class PoseCheck:
    """The field-fixed correction's measurements: joint error (cm, mean over the 24 joints and the training frames)
    of the capture's poses (``before``) and along the correction (``path``: (step, cm) pairs), ending at ``after``."""

    before: float
    after: float
    path: list[tuple[int, float]] = field(default_factory=list)

    @property
    def recovered(self) -> float:
        """The share of the joint error removed, ``1 - after / before``."""
        return 1 - self.after / self.before


@contextmanager
def field_fixed_trainer(
    field_run: Path, capture: Path, overrides: list[str] | tuple[str, ...] = (), frame_stride: int = 1
) -> Iterator:
    """The fit's own trainer (same rays, losses, optimiser and correction) on ``capture`` with the field of
    ``field_run`` loaded and frozen (part boxes and occupancy grid included): the run's config with today's pose
    correction settings (``train.pose_*``, whatever the field's run had), on from step 0, then ``overrides``. Its
    run folder is a temporary one."""
    from pipelines.runs.subject.session import start

    saved = read_run(field_run)
    today = {f"train.{k}={v}" for k, v in vars(TrainConfig()).items() if k.startswith("pose_")}
    sets = [
        f"data.subject={Path(capture).resolve()}",
        f"data.frame_stride={frame_stride}",
        *sorted(today),
        "train.pose_correction=true",
        "train.pose_start=0",
        "train.validate_every=0",
        *overrides,
    ]
    config = run_config(saved.state, saved.run_dir, sets)
    with tempfile.TemporaryDirectory(prefix="narf-pose-check-") as scratch:
        trainer = start(config, Path(scratch), torch.device("cpu"), progress=False)
        trainer.field.load_state_dict(saved.state["model"])
        for parameter in trainer.field.parameters():
            parameter.requires_grad_(False)
        yield trainer


@dataclass(frozen=True)
class PoseCheckRequest:
    """What :func:`correct_with_field_fixed` runs: the poses of ``capture``'s training frames corrected for ``steps``
    steps with the field of ``field_run`` (fitted on ``truth``'s exact poses) held fixed, the run's config changed by
    ``overrides``, every ``frame_stride``-th frame; the joint error measured every ``every`` steps."""

    field_run: Path
    capture: Path
    truth: Path
    steps: int
    overrides: tuple[str, ...] = ()
    every: int = 50
    frame_stride: int = 1


def correct_with_field_fixed(request: PoseCheckRequest) -> PoseCheck:
    """Run ``request`` (:class:`PoseCheckRequest`) with the fit's own trainer (:func:`field_fixed_trainer`)."""
    from pipelines.runs.subject.session import open_capture

    r = request
    with field_fixed_trainer(r.field_run, r.capture, r.overrides, r.frame_stride) as trainer:
        given = open_capture(trainer.config, quiet=True)
        reference, body = ZjuCapture(r.truth), BodyModel()
        frames = list(trainer.frames)

        def error() -> float:
            corrected = RefinedCapture(given, corrected_frames(trainer.pose_correction, given))
            return 100 * float(joint_errors(reference, corrected, body, frames).mean())

        before = 100 * float(joint_errors(reference, given, body, frames).mean())
        check = PoseCheck(before, before, [(0, before)])
        for step in range(1, r.steps + 1):
            trainer.train_step()
            if step % r.every == 0 or step == r.steps:
                check.path.append((step, error()))
        check.after = check.path[-1][1]
    return check


@dataclass
class ReferenceParams:
    """Body parameters of a capture's frames read from another folder of ZJU-MoCap params (docs/formats.md §1.6),
    named as the capture names its own params files: ``params(frame)`` as a capture has it."""

    capture: ZjuCapture
    folder: Path

    def params(self, frame: int) -> SmplParams:
        from pipelines.datasets.errors import CaptureError
        from pipelines.datasets.zju_mocap import param_index_from_image, read_params

        path = self.folder / f"{param_index_from_image(self.capture.ims[frame][0])[1]}.npy"
        if not path.is_file():
            raise CaptureError(f"{path}: missing (the reference has no params for capture frame {frame})")
        return read_params(path)


def reference_joint_errors(run, folder: Path) -> dict:
    """Mean joint error (cm, 24 joints, over the run's training frames) against the params in ``folder`` of the run's
    training poses (corrected where the fit corrected them) and of the capture's own: ``narf-eval
    --reference-params``. ``run``: a loaded subject run (``pipelines.runs.subject.session.LoadedRun``)."""
    frames = [int(f) for f in run.protocol.train_frames[:: run.config.data.frame_stride]]
    reference = ReferenceParams(run.capture, Path(folder))
    run_error = joint_errors(reference, run, run.body_model, frames)
    capture_error = joint_errors(reference, run.capture, run.body_model, frames)
    return {
        "reference": str(folder),
        "frames": len(frames),
        "corrected": bool(run.refined),
        "run_joint_error_cm": round(100 * float(run_error.mean()), 3),
        "capture_joint_error_cm": round(100 * float(capture_error.mean()), 3),
        "run_joint_error_p95_cm": round(100 * float(np.percentile(run_error, 95)), 3),
    }
