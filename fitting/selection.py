"""Which step a fit keeps: a score on held-back training frames, never on a test camera (docs/model.md §7, *The
step kept*).

With ``train.holdout_every`` n > 0 the session leaves every n-th training frame out of the training views; their
views (the training cameras at those frames) are the selection set. Every ``train.select_every`` steps the trainer
renders a fixed set of the set's person pixels (drawn once, seeded) at the evaluation sample counts and scores them
by the PSNR of their colour; the kept weights are stored beside the last ones, and a run is evaluated with them when
``train.keep`` is ``best``.

Which weights are kept: those of the best score so far (the *leader*), or of a later step whose score lies within
``train.select_margin`` paired standard errors of the leader's. The scores of two steps differ by the mean of the
rays' paired squared-error differences d_i = e_i(new) - e_i(leader); its standard error is std(d) / sqrt(R), in dB
10 / ln 10 times that over the leader's mean squared error (docs/model.md §7, *The step kept*). Late in an annealed
fit the score moves by about that much between checks, so a strict maximum keeps the first of equal scores.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import torch

from fitting.averaging import averaged_weights
from fitting.config import FitConfig
from fitting.data import RayBatch, TrainingSet
from fitting.losses import ray_colour_errors
from fitting.training_rays import render_training_rays
from narf.metrics import psnr

#: seed of the selection rays' draw: the same pixels at every score and in a resumed fit
SELECTION_SEED = 20211011


@dataclass
class Selection:
    """The selection set's fixed rays, the weights kept and the best score so far.

    Attributes:
        views: the held-back frames' views (their poses in ``views.poses``).
        rays: the fixed person-pixel rays the score renders.
        margin: ``train.select_margin``, in paired standard errors (0: the best score alone).
        best_step, best_psnr: the step of the weights kept and their score (dB); -1 and -inf before the first.
        best_model: the field's state_dict at ``best_step`` (on the CPU), or None.
        leader_step, leader_psnr: the step of the best score so far and the score.
        leader_errors: (R,) the rays' squared colour errors at ``leader_step`` (channel mean), or None.
        history: (step, PSNR) of every score.
    """

    views: TrainingSet
    rays: RayBatch
    margin: float = 0.0
    best_step: int = -1
    best_psnr: float = float("-inf")
    best_model: dict | None = None
    leader_step: int = -1
    leader_psnr: float = float("-inf")
    leader_errors: torch.Tensor | None = None
    history: list[tuple[int, float]] = field(default_factory=list)

    def update(self, step: int, errors: torch.Tensor, model: torch.nn.Module) -> bool:
        """Record the score of the rays' squared errors ``errors`` (R,) at ``step``; keep a copy of ``model``'s weights
        when the score leads, or lies within ``margin`` paired standard errors below the leader's. True if kept."""
        score = float(psnr(errors.mean()))
        self.history.append((step, score))
        leads = score > self.leader_psnr
        if leads:
            self.leader_step, self.leader_psnr, self.leader_errors = step, score, errors.detach().cpu().clone()
        elif self.leader_psnr - score > self.margin * paired_error_db(errors, self.leader_errors):
            return False
        self.best_step, self.best_psnr = step, score
        self.best_model = {k: v.detach().to("cpu", copy=True) for k, v in model.state_dict().items()}
        return True

    def errors(self, config: FitConfig, field: torch.nn.Module, camera_colour=None) -> torch.Tensor:
        """(R,) squared colour errors (channel mean) of ``field`` at the fixed person pixels, on the CPU:
        deterministic samples at the validation counts (``RenderConfig.validation_samples``), the field in eval mode
        (no jitter or dropout), ``camera_colour`` as the training loss applies it. Their mean's PSNR is the score."""
        r, poses, parts = config.render, self.views.poses, []
        training = field.training
        field.eval()
        with torch.no_grad():
            for start in range(0, self.rays.origins.shape[0], r.chunk):
                part = self.rays.take(slice(start, start + r.chunk))
                out = render_training_rays(
                    config,
                    field,
                    part.origins,
                    part.dirs,
                    part.frames,
                    poses,
                    *r.validation_samples(),
                    randomized=False,
                )
                parts.append(ray_colour_errors(config, out, part, camera_colour).cpu())
        field.train(training)
        return torch.cat(parts)

    def score(self, config: FitConfig, field: torch.nn.Module, camera_colour=None) -> float:
        """PSNR (dB) of the mean of :meth:`errors`."""
        return float(psnr(self.errors(config, field, camera_colour).mean()))

    def state(self) -> dict:
        """The checkpoint's ``selection`` entry."""
        return {
            "best_step": self.best_step,
            "best_psnr": self.best_psnr,
            "model": self.best_model,
            "leader_step": self.leader_step,
            "leader_psnr": self.leader_psnr,
            "leader_errors": self.leader_errors,
            "history": [list(item) for item in self.history],
        }

    def restore(self, state: dict) -> None:
        self.best_step, self.best_psnr = int(state["best_step"]), float(state["best_psnr"])
        self.best_model = copy.copy(state.get("model"))
        # checkpoints written before the margin: the leader is the best, its errors unknown (the next score leads)
        self.leader_step = int(state.get("leader_step", self.best_step))
        self.leader_psnr = float(state.get("leader_psnr", self.best_psnr))
        self.leader_errors = state.get("leader_errors")
        self.history = [(int(s), float(p)) for s, p in state.get("history", [])]


def paired_error_db(errors: torch.Tensor, reference: torch.Tensor | None) -> float:
    """Standard error (dB) of the PSNR difference between two scores of the same rays: with d = errors - reference
    (R,), (10 / ln 10) std(d) / (sqrt(R) mean(reference)), the first-order error of 10 log10 mean(errors) -
    10 log10 mean(reference). 0 without a ``reference`` (a restored leader whose errors were not stored)."""
    if reference is None or reference.shape != errors.shape or errors.numel() < 2:
        return 0.0
    difference = errors.double() - reference.double()
    spread = difference.std() / math.sqrt(errors.numel())
    return float(10 / math.log(10) * spread / reference.double().mean().clamp_min(1e-12))


def selection_set(views: TrainingSet, n_rays: int, margin: float = 0.0) -> Selection:
    """A :class:`Selection` over ``views`` with about ``n_rays`` person-pixel rays, spread evenly over the views;
    ``margin``: ``train.select_margin``."""
    generator = torch.Generator().manual_seed(SELECTION_SEED)
    per_view = max(1, n_rays // len(views))
    chosen = list(range(len(views)))
    rays = views.sample_images(chosen, per_view, 1.0, 0.0, generator)
    return Selection(views, rays, margin)


def kept_weights(state: dict, keep: str) -> tuple[dict, int]:
    """The weights a run is evaluated with and their step: the selection's best when ``keep`` is ``best`` and the
    checkpoint has one (the average's, with ``train.ema_decay``), else the last (averaged when the fit kept an
    average, ``fitting.averaging``)."""
    selection = state.get("selection") or {}
    if keep == "best" and selection.get("model") is not None:
        return selection["model"], int(selection["best_step"])
    averaged = averaged_weights(state)
    return (state["model"] if averaged is None else averaged), int(state["step"])
