"""Glue between a capture on disk and the fitting package: find the subject (real data, else the synthetic
stand-in), pose its frames, fit the part boxes, load the training views, and start (or resume) a Trainer."""

from __future__ import annotations

import json
import sys
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from fitting.checkpoint import CheckpointError
from fitting.config import FitConfig
from fitting.corrections import pose_correction_from_state
from fitting.data import FitData, TrainingSet
from fitting.distributed import SINGLE
from fitting.files import staged_folder
from fitting.fitted import SavedRun, load_fitted, read_run
from fitting.trainer import Trainer
from fitting.trainers import trainer_class
from narf.fields import model_spec
from narf.fields.common import PoseBatch, colour_from_nearest_place
from pipelines.body.locate import (
    BODY_MODEL_RECORD,
    body_model_record,
    check_record,
    default_smpl_dir,
    file_sha256,
    find_recorded,
    recorded_body_file,
)
from pipelines.body.mirror import MirroredSource
from pipelines.body.model import BodyModel, capture_poses, pose_batch
from pipelines.body.shells import part_shells
from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.smpl_files import cache_dir
from pipelines.datasets.subjects import data_root, find_subject, real_candidates, stand_in_notice, synthetic_path
from pipelines.datasets.zju_mocap import SmplParams
from pipelines.runs.subject.body_refine import RefinedCapture, RefineSettings, corrected_frames, refine_to_masks
from pipelines.runs.subject.outlines import outline_rays
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
        stand_in_notice(f"no real '{name}' capture under {root}; {state} the synthetic stand-in at {out}")
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


def poses_for_frames(source, body_model: BodyModel, frames: list[int], template_offsets=None):
    """PoseBatch, posed bodies and betas (F, 10) of capture frames, from their SMPL parameters; ``source``: the
    capture, or a loaded run (:class:`LoadedRun`: corrected poses on its training frames); ``template_offsets``:
    the capture's surface (``BodyModel.surface_offsets``), or None."""
    params = [source.params(f) for f in frames]
    stack = [torch.as_tensor(np.stack([getattr(p, k) for p in params])) for k in ("poses", "rh", "th", "shapes")]
    with torch.no_grad():
        bodies = body_model.pose_zju(*stack, template_offsets=template_offsets)
    return pose_batch(bodies), bodies, stack[3]


def training_poses(source, body_model: BodyModel, frames: list[int], chunk: int = 64) -> PoseBatch:
    """PoseBatch of many frames, posed ``chunk`` at a time: the posed vertices (80 kB a frame) are never all held;
    ``source`` as for :func:`poses_for_frames`."""
    parts = [poses_for_frames(source, body_model, frames[i : i + chunk])[0] for i in range(0, len(frames), chunk)]
    stacked = {k: [getattr(p, k) for p in parts] for k in PoseBatch.__dataclass_fields__}
    return PoseBatch(**{k: None if v[0] is None else torch.cat(v) for k, v in stacked.items()})


def fit_boxes(
    body_model: BodyModel, bodies, shapes: torch.Tensor, model, template_offsets=None
) -> tuple[tuple, torch.Tensor | None]:
    """Part boxes over the rest pose and the posed ``bodies`` (docs/model.md §1), and their shells (*Body shells*),
    or None where ``model.body_shell`` is 0 (whole boxes, as the paper); ``template_offsets``: the capture's
    surface, which ``bodies`` wear too (``BodyModel.surface_offsets``), or None. With a surface the shells' margin
    is ``model.surface_shell`` where that is set."""
    with torch.no_grad():
        rest = body_model.rest_body(shapes[:1], template_offsets)
        boxes = body_model.part_boxes([rest, bodies], model.box_scale_pad, model.box_abs_pad)
    if not model.body_shell:
        return boxes, None
    margin = model.surface_shell if template_offsets is not None and model.surface_shell else model.body_shell
    return boxes, part_shells([rest, bodies], body_model.faces, *boxes, model.shell_resolution, margin)


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


def capture_body_record(capture: ZjuCapture) -> dict | None:
    """The capture's record of the body model its params belong to (``body_model.json``), or None."""
    path = capture.root / BODY_MODEL_RECORD
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise CaptureError(f"{path}: unreadable ({err})") from None
    return check_record(record, str(path))


def fit_body_model(capture: ZjuCapture, state: dict | None) -> BodyModel:
    """The body model of a fit: a resumed run's recorded one; else the one ``--smpl-dir`` / ``$NARF_SMPL_DIR`` names,
    which must be the capture's when the capture records one; else the capture's recorded one, or the stand-in."""
    recorded = recorded_body_file(state or {}, "the checkpoint", "the run being resumed")
    if recorded is not None:
        return BodyModel(recorded)
    record = capture_body_record(capture)
    if record is None:
        return BodyModel()
    if not default_smpl_dir():
        return BodyModel(find_recorded(record, str(capture.root)))
    body = BodyModel()
    if file_sha256(body.path) != record["sha256"]:
        raise CaptureError(
            f"{capture.root / BODY_MODEL_RECORD}: the capture's params belong to {record['file']} (sha256 "
            f"{record['sha256'][:12]}...), not to {body.path}; fit with that body model (--smpl-dir)"
        )
    return body


def refines_bodies(config: FitConfig, n_cameras: int, surface: bool, progress: bool) -> bool:
    """Whether a fit refines its training frames' bodies against the training masks (docs/model.md §6, *Input
    corrections*): ``train.mask_body_iterations`` > 0 and a NeRF-type model, with two training cameras or more (one
    silhouette cannot place a body in depth: measured on a 1-view synthetic capture, 5.5 -> 9.0 cm of joint error),
    and, unless ``train.refine_surface_bodies``, bodies that do not wear the capture's fitted surface (``surface``:
    fitted by narf-prepare-capture to every camera's masks with the poses, so that the training cameras' masks alone
    only pull the bodies their way). Says why on stderr when it does not refine."""
    if config.train.mask_body_iterations <= 0 or not model_spec(config.model.name).rays:
        return False
    why = None
    if n_cameras < 2:
        why = "one training camera: the bodies are not refined against the masks"
    elif surface and not config.train.refine_surface_bodies:
        why = (
            "the capture's bodies wear a surface fitted to its masks (body_surface.npy): they are not refined against "
            "the training masks again (train.refine_surface_bodies=true does)"
        )
    if why and progress:
        print(f"narf: {why}", file=sys.stderr)
    return why is None


def build_fit_data(config: FitConfig, device, progress: bool = True, state: dict | None = None) -> FitData:
    """Load the protocol's training views (Neural Body order) into the view store, their poses and the part boxes.
    ``state``: the checkpoint of a fit being resumed (its body model is the recorded one)."""
    capture = open_capture(config)
    protocol = capture.protocol(config.data.protocol)
    frames, held_back = split_holdout(list(protocol.train_frames[:: config.data.frame_stride]), config.train)
    if config.train.holdout_every and not held_back and progress:
        print(
            f"narf: {len(frames)} training frames are too few to hold one in {config.train.holdout_every} back "
            f"(at least {2 * config.train.holdout_every}): every frame trains and the last step is kept",
            file=sys.stderr,
        )
    body_model = fit_body_model(capture, state)
    surface = body_model.surface_offsets(capture.surface_displacement(body_model.n_vertices))
    poses = training_poses(capture, body_model, frames)
    training = camera_views(capture, protocol, frames, poses, device, progress)
    source, refine = capture, refines_bodies(config, len(protocol.train_views), surface is not None, progress)
    if refine:  # a resumed fit trains on the bodies its checkpoint holds, never on a second refinement's
        kept = None if state is None else saved_bodies(state, capture)
        if kept is None:
            settings = RefineSettings(iterations=config.train.mask_body_iterations, progress=progress)
            kept = refine_to_masks(training, capture, body_model, frames, settings, surface)
        source = RefinedCapture(capture, kept)
        poses = training_poses(source, body_model, frames)
        training.poses = poses.to(device)
    mirrored = None
    if config.train.mirror_weight > 0:  # the bodies the fit trains on, in their mirror-image poses
        mirrored = training_poses(MirroredSource(source), body_model, frames).to(device)
    outlines = None
    if config.train.outline_weight > 0:  # the bodies the fit trains on, from cameras nobody recorded

        def pose_bodies(indices: list[int]):
            return poses_for_frames(source, body_model, [frames[i] for i in indices], surface)[1]

        outlines = outline_rays(pose_bodies, len(frames), body_model.faces, config.train.seed).to(device)
    _, bodies, shapes = poses_for_frames(source, body_model, box_frames(frames, config.data.box_frames), surface)
    boxes, shells = fit_boxes(body_model, bodies, shapes, config.model, surface)
    held_frame = frames[len(frames) // 2]
    gains = capture_gains(capture, config)
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
        capture_poses(source, body_model, frames) if config.train.pose_correction or refine else None,
        frames.index(held_frame),
        {"body_model": body_model_record(body_model.path), **gains_record(capture, gains)},
        held_back_views(
            capture,
            protocol,
            held_back,
            held_back_poses(capture, body_model, held_back, poses if borrows_colour(config) else None),
            device,
            progress,
        ),
        None if gains is None else torch.as_tensor(gains[list(protocol.train_views)]),
        shells,
        mirrored,
        outlines,
    )


def capture_gains(capture, config: FitConfig) -> np.ndarray | None:
    """(C, 3) the capture's measured colour gain per camera (``colour.json``), or None where it has none or
    ``data.camera_gains`` is off: what a fit trains and is evaluated with (docs/model.md §6)."""
    return capture.camera_gains if config.data.camera_gains else None


def gains_record(capture, gains: np.ndarray | None) -> dict:
    """The checkpoint's record of the camera gains the fit trained with (``camera_gains``: name -> [r, g, b])."""
    if gains is None:
        return {}
    return {"camera_gains": {c.name: [float(v) for v in g] for c, g in zip(capture.cameras, gains)}}


def split_holdout(frames: list[int], train) -> tuple[list[int], list[int]]:
    """The training frames that train and those held back to choose the step kept (``train.holdout_every`` n: the
    middle frame of every n, so that each held-back frame lies between trained ones; fitting.selection). Fewer than
    2n frames hold none back (a short capture loses no frame to it; :func:`build_fit_data` says so)."""
    n = train.holdout_every
    if n <= 0 or len(frames) < 2 * n:  # too few to hold two back: every frame trains, the last step is kept
        return frames, []
    held = set(frames[n // 2 :: n])
    return [f for f in frames if f not in held], sorted(held)


def camera_views(capture, protocol, frames: list[int], poses, device, progress: bool) -> TrainingSet:
    """The training cameras' usable views of ``frames`` (Neural Body order) in the view store, with ``poses`` (one
    per frame) and each view's training camera (0..C-1)."""
    items = [(i, f, c) for i, f in enumerate(frames) for _, c in protocol.usable([f], protocol.train_views)]
    views = decoded_views(capture, [(f, c) for _, f, c in items], progress)
    slots = [list(protocol.train_views).index(c) for _, _, c in items]
    store = cache_dir() / "views"
    return TrainingSet(views, [i for i, _, _ in items], poses, device, store_dir=store, camera_of_view=slots)


def borrows_colour(config: FitConfig) -> bool:
    """Frames the fit does not train on take their colour's pose features from the nearest trained frame
    (``model.novel_colour``, docs/model.md §4, *Colour of frames not trained on*)."""
    return config.model.novel_colour == "nearest" and not model_spec(config.model.name).pose_in_density


def held_back_poses(capture, body_model: BodyModel, frames: list[int], bank=None):
    """The held-back ``frames``' poses in the capture (None when there are none), coloured as the evaluation colours
    them: with ``bank`` (the trained frames' poses, where :func:`borrows_colour`), the pose features of the trained
    frame standing nearest."""
    if not frames:
        return None
    poses = training_poses(capture, body_model, frames)
    if bank is not None:
        poses = colour_from_nearest_place(
            poses, bank.to(poses.reach.device), torch.zeros(len(frames), dtype=torch.bool)
        )
    return poses


def held_back_views(capture, protocol, frames: list[int], poses, device, progress: bool):
    """The training cameras' views of the held-back ``frames`` in ``poses`` (:func:`held_back_poses`); None when
    there are none."""
    if not frames:
        return None
    return camera_views(capture, protocol, frames, poses, device, progress)


def start(
    config: FitConfig, run_dir: Path, device, state: dict | None = None, progress: bool = True, processes=SINGLE
) -> Trainer:
    """A Trainer (the CNN baseline: a CnnTrainer) on the config's capture; ``state``: the checkpoint it resumes.
    ``processes``: this process's place in a data-parallel fit (``fitting.distributed``)."""
    data = build_fit_data(config, device, progress and processes.is_main, state)
    trainer = trainer_class(config)
    if trainer is not Trainer:  # the CNN baseline
        if processes.distributed:
            raise ValueError("data-parallel fitting (torchrun) covers the NeRF-type models; fit the CNN as one process")
        return trainer(config, run_dir, device, data, state=state, progress=progress)
    return trainer(config, run_dir, device, data, state=state, progress=progress, processes=processes)


@dataclass
class LoadedRun:
    """A fitted run ready to render: its config, model (eval mode), capture, protocol and body model; ``refined``
    the corrected body parameters of its training frames (empty without pose correction); ``mesh_level`` the record
    of the mesh level chosen from the fit, once it has been (``pipelines.runs.subject.mesh``)."""

    config: FitConfig
    field: torch.nn.Module
    capture: ZjuCapture
    protocol: object
    body_model: BodyModel
    step: int
    mesh_level: dict | None = None
    refined: dict[int, SmplParams] = field(default_factory=dict)
    other: ZjuCapture | None = None  #: another capture being evaluated (``narf-eval --capture``)
    last_step: int | None = None  #: the fit's last step (``step`` is that of the weights kept: fitting.selection)
    colour_bank: tuple | None = None  #: the trained frames' poses and numbers, once :meth:`colour_poses` needs them

    def params(self, frame: int) -> SmplParams:
        """A frame's body parameters as the run shows it: corrected for a training frame of a fit that corrected its
        poses, the capture's otherwise (held-out frames have no images to correct them with)."""
        return self.refined[frame] if frame in self.refined else self.capture.params(frame)

    def trained_frames(self) -> list[int]:
        """The capture frames the fit trained on (its training frames less those held back, :func:`split_holdout`)."""
        return split_holdout(list(self.protocol.train_frames[:: self.config.data.frame_stride]), self.config.train)[0]

    @cached_property
    def _colour_bank(self) -> tuple[PoseBatch, set[int]]:
        """The trained frames' poses and numbers, posed once when :meth:`colour_poses` first needs them."""
        trained = self.trained_frames()
        return training_poses(self, self.body_model, trained), set(trained)

    def colour_poses(self, poses: PoseBatch, frames: list[int] | None = None) -> PoseBatch:
        """``poses`` with the colour's pose features the run renders them with (``model.novel_colour``, docs/model.md
        §4, *Colour of frames not trained on*): ``frames``, the run's capture frames they pose (None: other frames,
        such as another recording's or a new motion's); the trained ones keep their own, the others borrow those of
        the trained frame standing nearest. Unchanged for ``own`` and for models whose density reads them."""
        if not borrows_colour(self.config):
            return poses
        bank, trained = self._colour_bank
        keep = torch.tensor([f in trained for f in frames] if frames is not None else [False] * poses.reach.shape[0])
        return colour_from_nearest_place(poses, bank, keep)


def refined_params(state: dict, capture: ZjuCapture, path: Path) -> dict[int, SmplParams]:
    """The corrected parameters of a checkpoint's training frames (capture frame -> SmplParams), {} without."""
    try:
        correction = pose_correction_from_state(state)
    except (KeyError, RuntimeError, TypeError, ValueError) as err:
        raise CheckpointError(f"{path}: its pose correction is unreadable ({err})") from None
    return {} if correction is None else corrected_frames(correction, capture)


def saved_bodies(state: dict, capture: ZjuCapture) -> dict[int, SmplParams] | None:
    """The training frames' bodies a checkpoint's pose correction starts from (the capture's, refined against the
    masks), without its corrections: what a resumed fit trains on (None: the checkpoint has no pose correction)."""
    correction = pose_correction_from_state(state)
    if correction is None:
        return None
    with torch.no_grad():
        for parameter in correction.parameters():
            parameter.zero_()
    return corrected_frames(correction, capture)


def load_run(run: Path | SavedRun, device="cpu") -> LoadedRun:
    """Load a run folder written by ``narf-fit --out`` (checkpoint, config, the capture it was fitted on, its body
    model and its corrected poses); ``run``: the folder, or its checkpoint already read."""
    saved = read_run(run)
    fitted = load_fitted(saved, device, kind="subject")  # the kind is checked before a capture is read or generated
    source = f"{saved.run_dir / 'checkpoint.pt'}"
    body = BodyModel(recorded_body_file(fitted.state, source, str(saved.run_dir)))  # None: the stand-in
    capture = open_capture(fitted.config, quiet=True)
    protocol = capture.protocol(fitted.config.data.protocol)
    refined = refined_params(fitted.state, capture, Path(source))
    kept = fitted.step if fitted.kept_step is None else fitted.kept_step
    return LoadedRun(fitted.config, fitted.field, capture, protocol, body, kept, refined=refined, last_step=fitted.step)


REFINED = "refined_params"


def write_refined_params(run_dir: Path) -> Path | None:
    """Write the run's corrected training poses as ZJU-MoCap params (``RUN/refined_params/<i>.npy``, docs/formats.md
    §1.6, named as the capture names its params files) for other tools; staged, then moved into place. None for a
    fit without pose correction."""
    from pipelines.datasets.zju_mocap import param_index_from_image, write_params

    saved = read_run(Path(run_dir))
    state, config, run_dir = saved.state, saved.config, saved.run_dir
    if state.get("pose_correction") is None:
        return None
    capture = open_capture(config, quiet=True)
    refined = refined_params(state, capture, run_dir / "checkpoint.pt")
    with staged_folder(run_dir / REFINED) as partial:
        for frame, params in refined.items():
            write_params(partial / f"{param_index_from_image(capture.ims[frame][0])[1]}.npy", params)
    return run_dir / REFINED
