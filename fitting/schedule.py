"""The learning rate over a fit: upstream's per-step decay, and an optional anneal at the end of the fit's budget
(docs/model.md §6, *The learning rate*)."""

from __future__ import annotations

import time
from collections.abc import Callable


def lr_factor(step: int, progress: float, decay: float, floor: float, anneal: float, anneal_to: float) -> float:
    """The learning rate's multiplier at ``step``, a fraction ``progress`` in [0, 1] through the fit's budget.

    factor = max(decay^step, floor) · a(progress), with a(p) = 1 for p <= 1 - anneal and
    a(p) = anneal_to^((p - 1 + anneal) / anneal) after: an exponential fall to ``anneal_to`` over the last
    ``anneal`` of the budget (``anneal`` = 0: upstream's decay alone).
    """
    factor = max(decay**step, floor)
    if anneal <= 0:
        return factor
    into = (min(max(progress, 0.0), 1.0) - 1.0 + anneal) / anneal
    return factor * anneal_to ** max(into, 0.0)


class Budget:
    """How far a fit is through its budget: ``steps`` optimisation steps or ``minutes`` of this invocation's wall
    clock (None: steps only), whichever ends first. The clock starts at construction and is read at :meth:`tick`,
    once a step, so that every process of a data-parallel fit agrees on it (``agree``: the largest over processes)."""

    def __init__(self, steps: int, minutes: float | None = None):
        self.steps, self.minutes = steps, minutes
        self._started, self._clock = time.perf_counter(), 0.0

    def tick(self, agree: Callable[[float], float] = float) -> None:
        """Read the clock: the fraction of the minutes spent, agreed between processes."""
        if self.minutes is not None:
            self._clock = agree((time.perf_counter() - self._started) / (60 * self.minutes))

    @property
    def out_of_time(self) -> bool:
        return self.minutes is not None and self._clock >= 1.0

    def progress(self, step: int) -> float:
        """max(step / steps, the clock's fraction at the last tick), in [0, 1]."""
        return min(max(step / max(self.steps, 1), self._clock), 1.0)
