"""An exponential moving average of the field's weights (Polyak averaging; docs/model.md §7, *The weights kept*).

With ``train.ema_decay`` β > 0 the trainer keeps, beside the weights Adam moves, their average

    W̄_0 = W_0,    W̄_t = β W̄_{t-1} + (1 - β) W_t,

over the field's parameters (buffers such as the occupancy grid and the shells are the live field's). The average
is what the held-back frames score, what the selection keeps and what a run is evaluated with; the optimiser keeps
training the raw weights, so averaging changes no training step. A few thousand Adam steps of a few hundred rays
each leave the last weights scattered about where the fit is heading; the average of the last ~1/(1 - β) steps lies
nearer it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
from torch.optim.swa_utils import get_ema_multi_avg_fn


class WeightAverage:
    """The moving average of ``module``'s parameters with decay ``decay`` (0 < β < 1), starting at their values now.

    Attributes:
        decay: β.
        updates: steps averaged so far.
        average: name -> averaged parameter (float tensors on the module's device, detached).
    """

    def __init__(self, module: torch.nn.Module, decay: float):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"the weights' average needs a decay in (0, 1), got {decay!r}")
        self.decay, self.updates = decay, 0
        self._update = get_ema_multi_avg_fn(decay)
        self.average = {name: p.detach().clone() for name, p in module.named_parameters()}

    @torch.no_grad()
    def update(self, module: torch.nn.Module) -> None:
        """W̄ <- β W̄ + (1 - β) W for every parameter W of ``module`` (one foreach lerp)."""
        current = dict(module.named_parameters())
        self._update(list(self.average.values()), [current[name].detach() for name in self.average], self.updates)
        self.updates += 1

    @contextlib.contextmanager
    def applied(self, module: torch.nn.Module) -> Iterator[None]:
        """Within the block ``module`` holds the averaged parameters; its own come back after it."""
        params = dict(module.named_parameters())
        own = {name: p.detach().clone() for name, p in params.items()}
        with torch.no_grad():
            for name, value in self.average.items():
                params[name].copy_(value)
        try:
            yield
        finally:
            with torch.no_grad():
                for name, value in own.items():
                    params[name].copy_(value)

    def state(self) -> dict:
        """The checkpoint's ``weight_average`` entry."""
        return {"decay": self.decay, "updates": self.updates, "average": dict(self.average)}

    def restore(self, state: dict) -> None:
        """Take a checkpoint's entry back (its parameter names must be this module's)."""
        missing = set(self.average) ^ set(state["average"])
        if missing:
            raise ValueError(f"the checkpoint's weight average does not fit this model ({sorted(missing)[0]})")
        for name, value in state["average"].items():
            self.average[name].copy_(value)
        self.updates = int(state["updates"])


def averaged_weights(state: dict) -> dict | None:
    """The averaged weights of a checkpoint's last step (its model's state_dict with the averaged parameters), or
    None when the fit kept no average."""
    entry = state.get("weight_average")
    if not isinstance(entry, dict) or not isinstance(entry.get("average"), dict):
        return None
    return {**state["model"], **entry["average"]}
