"""Glue between a capture on disk and the fitting package: find the subject (real data, else the synthetic
stand-in), pose its frames, fit the part boxes, load the training views, and start (or resume) a Trainer."""

from __future__ import annotations

import sys
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from fitting.config import FitConfig
from fitting.data import FitData, TrainingSet
from fitting.distributed import SINGLE
from fitting.fitted import load_fitted
from fitting.trainer import Trainer
from narf.fields.common import PoseBatch
from pipelines.body.model import BodyModel, pose_batch
from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.smpl_files import cache_dir
from pipelines.datasets.subjects import data_root, find_subject, real_candidates, synthetic_path
from pipelines.datasets.zju_mocap import CaptureError
from pipelines.synthetic.capture import SYNTHETIC_SUBJECTS, SynthConfig, generate_capture, is_complete


def resolve_subject(name: str, root: str | Path | None = None, generate: bool = True, quiet: bool = False) -> Path:
    """Folder of subject ``name``: its real capture (``find_subject``), else the synthetic stand-in under
    ``<root>/synthetic/<name>``, generated when missing and announced in one line on stderr.

    Raises:
        CaptureError: no real data and no synthetic stand-in for this name, or (``generate=False``) the stand-in
            is not generated yet.
    """
    real = find_subject(name, root)
    if real is not None:
        return real
    root = data_root(root)
    key = name.lower()
    if key not in SYNTHETIC_SUBJECTS and Path(name).is_dir():  # a folder was named: say what it lacks
        raise CaptureError(
            f"{name}: no annots.npy, so not a ZJU-MoCap subject folder (narf-prepare-capture makes one from a "
            "recording)"
        )
    if key not in SYNTHETIC_SUBJECTS:
        looked = ", ".join(dict.fromkeys(str(p) for p in real_candidates(name, root)[:3]))
        raise CaptureError(
            f"no subject '{name}' under {root} (looked in {looked}, ...); synthetic stand-ins exist "
            f"for: {', '.join(SYNTHETIC_SUBJECTS)}"
        )
    out = synthetic_path(key, root)
    if not quiet:
        state = "using" if is_complete(out) else "generating"
        print(f"narf: no real '{name}' capture under {root}; {state} the synthetic stand-in at {out}", file=sys.stderr)
    if not is_complete(out):
        if not generate:
            raise CaptureError(f"{out}: synthetic capture not generated yet (run narf-synth --subject {key})")
        generate_capture(out, SynthConfig(subject=key))
    return out


def open_capture(config: FitConfig, quiet: bool = False) -> ZjuCapture:
    """The subject of a config, read with the config's loader options."""
    root = resolve_subject(config.data.subject, config.data.data_root, quiet=quiet)
    return ZjuCapture(
        root,
        ratio=config.data.ratio,
        mask_source=config.data.mask_source,
        new_params=config.data.new_params,
        white_background=config.data.white_background,
    )


def poses_for_frames(capture: ZjuCapture, body_model: BodyModel, frames: list[int]):
    """PoseBatch, posed bodies and betas (F, 10) of capture frames, from their SMPL parameters."""
    params = [capture.params(f) for f in frames]
    stack = [torch.as_tensor(np.stack([getattr(p, k) for p in params])) for k in ("poses", "rh", "th", "shapes")]
    with torch.no_grad():
        bodies = body_model.pose_zju(*stack)
    return pose_batch(bodies), bodies, stack[3]


def training_poses(capture: ZjuCapture, body_model: BodyModel, frames: list[int], chunk: int = 64) -> PoseBatch:
    """PoseBatch of many frames, posed ``chunk`` at a time: the posed vertices (80 kB a frame) are never all held."""
    parts = [poses_for_frames(capture, body_model, frames[i : i + chunk])[0] for i in range(0, len(frames), chunk)]
    return PoseBatch(*(torch.cat([getattr(p, k) for p in parts]) for k in PoseBatch.__dataclass_fields__))


def fit_boxes(body_model: BodyModel, bodies, shapes: torch.Tensor, scale_pad: float, abs_pad: float):
    """Part boxes over the rest pose and the posed ``bodies`` (docs/model.md §1)."""
    with torch.no_grad():
        rest = body_model.rest_body(shapes[:1])
        return body_model.part_boxes([rest, bodies], scale_pad, abs_pad)


def box_frames(frames: list[int], count: int) -> list[int]:
    """Up to ``count`` evenly spaced frames of ``frames``, the ones the part boxes are fitted on."""
    return [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, min(count, len(frames))).astype(int))]


def decoded_views(capture: ZjuCapture, items: list[tuple[int, int]], progress: bool, ahead: int = 8):
    """The views (frame, camera) of ``items``, decoded by two threads and yielded in order, at most ``ahead`` of
    them decoded and not yet taken: memory does not grow with the number of views."""
    progress_bar = tqdm(total=len(items), desc="loading training views", unit="image", disable=not progress)
    with progress_bar as bar, ThreadPoolExecutor(2) as pool:  # closed before an error propagates to its message
        pending = deque()
        for frame, camera in items:
            pending.append(pool.submit(capture.load_frame, frame, camera))
            if len(pending) >= ahead:
                bar.update()
                yield pending.popleft().result()
        while pending:
            bar.update()
            yield pending.popleft().result()


def build_fit_data(config: FitConfig, device, progress: bool = True) -> FitData:
    """Load the protocol's training views (Neural Body order) into the view store, their poses and the part boxes."""
    capture = open_capture(config)
    protocol = capture.protocol(config.data.protocol)
    frames = list(protocol.train_frames[:: config.data.frame_stride])
    body_model = BodyModel()
    poses = training_poses(capture, body_model, frames)
    _, bodies, shapes = poses_for_frames(capture, body_model, box_frames(frames, config.data.box_frames))
    boxes = fit_boxes(body_model, bodies, shapes, config.model.box_scale_pad, config.model.box_abs_pad)
    items = [(i, f, c) for i, f in enumerate(frames) for _, c in protocol.usable([f], protocol.train_views)]
    views = decoded_views(capture, [(f, c) for _, f, c in items], progress)
    training = TrainingSet(views, [i for i, _, _ in items], poses, device, store_dir=cache_dir() / "views")
    held_frame = frames[len(frames) // 2]
    held_view = protocol.test_views[0] if protocol.test_views else protocol.train_views[0]

    def validation():
        item = capture.load_frame(held_frame, held_view)
        return item.image, item.camera, poses.select(torch.tensor([frames.index(held_frame)]))

    return FitData(
        training,
        boxes,
        frames,
        validation,
        f"{capture.root}: {len(training)} training images ({len(frames)} frames x {len(protocol.train_views)} views)",
    )


def start(
    config: FitConfig, run_dir: Path, device, state: dict | None = None, progress: bool = True, processes=SINGLE
) -> Trainer:
    """A Trainer (the CNN baseline: a CnnTrainer) on the config's capture; ``state``: the checkpoint it resumes.
    ``processes``: this process's place in a data-parallel fit (``fitting.distributed``)."""
    data = build_fit_data(config, device, progress and processes.is_main)
    if config.model.name == "cnn":
        from fitting.cnn_trainer import CnnTrainer

        if processes.distributed:
            raise ValueError("data-parallel fitting (torchrun) covers the NeRF-type models; fit the CNN as one process")
        return CnnTrainer(config, run_dir, device, data, state=state, progress=progress)
    return Trainer(config, run_dir, device, data, state=state, progress=progress, processes=processes)


@dataclass
class LoadedRun:
    """A fitted run ready to render: its config, model (eval mode), capture, protocol and body model; ``mesh_level``
    the record of the mesh level chosen from the fit, once it has been (``pipelines.runs.subject.mesh``)."""

    config: FitConfig
    field: torch.nn.Module
    capture: ZjuCapture
    protocol: object
    body_model: BodyModel
    step: int
    mesh_level: dict | None = None


def load_run(run_dir: Path, device="cpu") -> LoadedRun:
    """Load a run folder written by ``narf-fit --out`` (checkpoint, config, and the capture it was fitted on)."""
    fitted = load_fitted(run_dir, device, kind="subject")  # the kind is checked before a capture is read or generated
    capture = open_capture(fitted.config, quiet=True)
    protocol = capture.protocol(fitted.config.data.protocol)
    return LoadedRun(fitted.config, fitted.field, capture, protocol, BodyModel(), fitted.step)
