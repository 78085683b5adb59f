"""The capture's bodies refined against its masks before a subject fit (docs/guides/fitting.md, *Bodies refined
against the masks*): the training frames' SMPL poses, the global turns and the translations move so that the posed
body's projection covers each training view's mask and no more (``pipelines.body.silhouettes``), under a robust pull
towards the bodies the capture gives.

``E = w_s (E_out + E_in) + w_p mean_f sum_j rho(|d_fj|^2 / s^2)``, with d_fj the change of frame f's joint j
(axis-angle, the global turn Rh included) and s the prior's scale; the shapes stay. All frames take one Adam step
per iteration, on every ``vertex_stride``-th vertex.

The masks see where each limb is, not how it turns about its own axis: a bone's twist is left to the photometric
pose correction that follows (``fitting.corrections.PoseCorrection``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import cv2
import numpy as np
import torch
from tqdm import tqdm

from fitting.corrections import robust
from fitting.data import TrainingSet
from pipelines.body.model import BodyModel
from pipelines.body.silhouettes import SilhouetteSettings, SilhouetteTerm, adam_stage, silhouette_targets
from pipelines.datasets.zju_mocap import SmplParams


@dataclass(frozen=True)
class RefineSettings:
    """The refinement's settings (module docstring)."""

    iterations: int = 150
    lr: float = 0.01
    silhouette_weight: float = 1.0
    prior_weight: float = 1e-2
    prior_degrees: float = 10.0
    silhouette: SilhouetteSettings = field(
        default_factory=lambda: SilhouetteSettings(height=256, outline_points=150, vertex_stride=4)
    )
    progress: bool = True  #: a progress bar over the iterations


@dataclass
class RefinedCapture:
    """A capture whose frames in ``refined`` (capture frame -> SmplParams) have other bodies; ``params(frame)`` as a
    capture has it."""

    capture: object
    refined: dict[int, SmplParams]

    def params(self, frame: int) -> SmplParams:
        return self.refined[frame] if frame in self.refined else self.capture.params(frame)


def corrected_frames(correction, capture) -> dict[int, SmplParams]:
    """The training frames' parameters a pose correction (``fitting.corrections.PoseCorrection``) shows, as they
    stand (capture frame -> SmplParams, the shapes ``capture``'s)."""
    poses, rh, th = (v.float().cpu().numpy() for v in correction.zju_params())
    frames = [int(f) for f in correction.frames]
    return {f: SmplParams(poses[i], rh[i], th[i], capture.params(f).shapes) for i, f in enumerate(frames)}


def _view_masks(training: TrainingSet, n_frames: int, height: int):
    """Per training frame and camera: the view's mask and its pixels of unknown owner (docs/formats.md §1.5), each
    reduced to at most ``height`` rows (or None), the views' full sizes (SimpleNamespace width / height per camera)
    and projections P (C, 3, 4) ``K [R | t]``."""
    n_cameras = training.n_cameras
    masks = [[None] * n_cameras for _ in range(n_frames)]
    unknown = [[None] * n_cameras for _ in range(n_frames)]
    sizes, P = [None] * n_cameras, torch.zeros(n_cameras, 3, 4)
    for view in range(len(training)):
        frame, camera = int(training.frame_of_image[view]), int(training.camera_of_image[view])
        mask, hidden = training.store.mask_and_unknown(view)
        rows, cols = mask.shape
        if sizes[camera] is None:
            sizes[camera] = SimpleNamespace(width=cols, height=rows)
            P[camera] = (training.Ks[view] @ training.cam_from_world[view, :3]).cpu()
        scale = min(1.0, height / rows)
        size = (max(1, round(cols * scale)), max(1, round(rows * scale)))
        masks[frame][camera], unknown[frame][camera] = (
            cv2.resize(m.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.5 for m in (mask, hidden)
        )
    return masks, unknown, sizes, P


def refine_to_masks(
    training: TrainingSet,
    source,
    body: BodyModel,
    frames: list[int],
    settings: RefineSettings = RefineSettings(),
    template_offsets=None,
) -> dict[int, SmplParams]:
    """The training frames' bodies refined against their views' masks (module docstring): capture frame ->
    SmplParams. ``source``: the capture (anything with ``params(frame)``); ``frames``: the capture frame of each
    training frame (``training.frame_of_image`` indexes them); ``template_offsets``: the capture's surface
    (``BodyModel.surface_offsets``), or None."""
    params = [source.params(f) for f in frames]
    poses0, rh0, th0, shapes = (
        torch.as_tensor(np.stack([getattr(p, k) for p in params]), dtype=torch.float32)
        for k in ("poses", "rh", "th", "shapes")
    )
    masks, unknown, sizes, P = _view_masks(training, len(frames), settings.silhouette.height)
    stride = settings.silhouette.vertex_stride  # only the vertices the term reads are posed
    term = SilhouetteTerm(
        silhouette_targets(sizes, masks, settings.silhouette, unknown), P.numpy(), settings.silhouette
    )
    d_poses = torch.zeros(len(frames), 23, 3, requires_grad=True)
    d_rh = torch.zeros(len(frames), 3, requires_grad=True)
    d_th = torch.zeros(len(frames), 3, requires_grad=True)
    scale2 = math.radians(settings.prior_degrees) ** 2

    def refined_poses() -> torch.Tensor:  # (F, 72): the global turn stays in Rh
        return torch.cat([poses0[:, :3], poses0[:, 3:] + d_poses.reshape(len(frames), -1)], dim=1)

    def posed(every: int) -> torch.Tensor:
        args = (refined_poses(), rh0 + d_rh, th0 + d_th, shapes, every)
        return body.vertices_zju(*args, template_offsets=template_offsets)

    def energy() -> torch.Tensor:
        turns = torch.cat([d_poses, d_rh[:, None]], dim=1).pow(2).sum(-1) / scale2
        prior = robust(turns).sum(-1).mean()
        return settings.silhouette_weight * term(posed(stride), strided=True) + settings.prior_weight * prior

    bar = tqdm(total=settings.iterations, desc="refining bodies to masks", unit="it", disable=not settings.progress)
    with bar:
        adam_stage(energy, [d_poses, d_rh, d_th], settings.iterations, settings.lr, bar.update)
    with torch.no_grad():
        poses = refined_poses().numpy()
        rh, th = (rh0 + d_rh).numpy(), (th0 + d_th).numpy()
    return {f: SmplParams(poses[i], rh[i], th[i], params[i].shapes) for i, f in enumerate(frames)}
