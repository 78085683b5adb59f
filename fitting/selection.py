"""Which step a fit keeps: a score on held-back training frames, never on a test camera (docs/model.md §7, *The
step kept*).

With ``train.holdout_every`` n > 0 the session leaves every n-th training frame out of the training views; their
views (the training cameras at those frames) are the selection set. Every ``train.select_every`` steps the trainer
renders a fixed set of the set's person pixels (drawn once, seeded) at the evaluation sample counts and scores them
by the PSNR of their colour; the best-scoring weights are kept beside the last ones, and a run is evaluated with them
when ``train.keep`` is ``best``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import torch

from fitting.averaging import averaged_weights
from fitting.config import FitConfig
from fitting.data import RayBatch, TrainingSet
from fitting.losses import ray_loss
from narf.metrics import psnr

#: seed of the selection rays' draw: the same pixels at every score and in a resumed fit
SELECTION_SEED = 20211011


@dataclass
class Selection:
    """The selection set's fixed rays and the best score so far.

    Attributes:
        views: the held-back frames' views (their poses in ``views.poses``).
        rays: the fixed person-pixel rays the score renders.
        best_step, best_psnr: the step of the best score and the score (dB); -1 and -inf before the first.
        best_model: the field's state_dict at ``best_step`` (on the CPU), or None.
        history: (step, PSNR) of every score.
    """

    views: TrainingSet
    rays: RayBatch
    best_step: int = -1
    best_psnr: float = float("-inf")
    best_model: dict | None = None
    history: list[tuple[int, float]] = field(default_factory=list)

    def update(self, step: int, score: float, model: torch.nn.Module) -> bool:
        """Record ``score`` at ``step``; keep a copy of ``model``'s weights when it is the best. True if it was."""
        self.history.append((step, score))
        if score <= self.best_psnr:
            return False
        self.best_step, self.best_psnr = step, score
        self.best_model = {k: v.detach().to("cpu", copy=True) for k, v in model.state_dict().items()}
        return True

    def score(self, config: FitConfig, field: torch.nn.Module, camera_colour=None) -> float:
        """PSNR (dB) of ``field``'s colour at the fixed person pixels, deterministic samples at the evaluation counts,
        the field in eval mode (no jitter or dropout); ``camera_colour`` as the training loss applies it."""
        r, squared, count = config.render, 0.0, 0
        training = field.training
        field.eval()
        with torch.no_grad():
            for start in range(0, self.rays.origins.shape[0], r.chunk):
                part = self.rays.take(slice(start, start + r.chunk))
                _, colour = ray_loss(
                    config,
                    field,
                    part,
                    self.views.poses,
                    None,
                    r.eval_coarse,
                    r.eval_fine,
                    randomized=False,
                    camera_colour=camera_colour,
                )
                squared, count = squared + float(colour) * part.rgb.numel(), count + part.rgb.numel()
        field.train(training)
        return float(psnr(torch.tensor(squared / max(count, 1))))

    def state(self) -> dict:
        """The checkpoint's ``selection`` entry."""
        return {
            "best_step": self.best_step,
            "best_psnr": self.best_psnr,
            "model": self.best_model,
            "history": [list(item) for item in self.history],
        }

    def restore(self, state: dict) -> None:
        self.best_step, self.best_psnr = int(state["best_step"]), float(state["best_psnr"])
        self.best_model = copy.copy(state.get("model"))
        self.history = [(int(s), float(p)) for s, p in state.get("history", [])]


def selection_set(views: TrainingSet, n_rays: int) -> Selection:
    """A :class:`Selection` over ``views`` with about ``n_rays`` person-pixel rays, spread evenly over the views."""
    generator = torch.Generator().manual_seed(SELECTION_SEED)
    per_view = max(1, n_rays // len(views))
    chosen = list(range(len(views)))
    rays = views.sample_images(chosen, per_view, 1.0, 0.0, generator)
    return Selection(views, rays)


def kept_weights(state: dict, keep: str) -> tuple[dict, int]:
    """The weights a run is evaluated with and their step: the selection's best when ``keep`` is ``best`` and the
    checkpoint has one (the average's, with ``train.ema_decay``), else the last (averaged when the fit kept an
    average, ``fitting.averaging``)."""
    selection = state.get("selection") or {}
    if keep == "best" and selection.get("model") is not None:
        return selection["model"], int(selection["best_step"])
    averaged = averaged_weights(state)
    return (state["model"] if averaged is None else averaged), int(state["step"])
