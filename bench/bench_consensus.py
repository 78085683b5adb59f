"""The consensus of views (``pipelines.prepare.people.multiview.consensus``) against its one-pair-at-a-time reference,
on crowded scenes of 8 views (``pipelines.synthetic.crowd``): milliseconds per call, 1 and 3 people."""

from __future__ import annotations

import time

import numpy as np

from pipelines.prepare.people.multiview import consensus, consensus_reference
from pipelines.synthetic.crowd import HEIGHT, crowded_scene


def _ms(search, P, views, heights) -> float:
    start, calls = time.perf_counter(), 0
    while time.perf_counter() - start < 3.0 or calls < 3:
        search(P, views, heights, 0.05)
        calls += 1
    return 1000 * (time.perf_counter() - start) / calls


def run() -> list[dict]:
    rows = []
    for people in (1, 3):
        P, views, _ = crowded_scene(np.random.default_rng(1), 8, people)
        heights = np.full(len(P), HEIGHT)
        fast, slow = _ms(consensus, P, views, heights), _ms(consensus_reference, P, views, heights)
        label = f"consensus of 8 views, {people} {'person' if people == 1 else 'people'}"
        rows.append({"benchmark": label, "ms per call": round(fast, 1), "reference ms": round(slow, 1)})
    return rows
