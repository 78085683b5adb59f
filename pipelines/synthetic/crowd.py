"""Random crowded multi-view scenes for the consensus of views (``pipelines.prepare.people.multiview.consensus``):
cameras on a circle, people as clouds of targets, per view each person's detection (pixel noise, missing joints) and a
scrambled copy, now and then a false person and a missed one. The test oracle and the benchmark share them
(tests/test_consensus.py, ``python -m bench consensus``)."""

from __future__ import annotations

import numpy as np

N_TARGETS = 20
HEIGHT = 480.0


def cameras(rng, n_views: int) -> np.ndarray:
    """(V, 3, 4) projections of cameras on a 4 m circle looking at the origin, f = 500 px, 640 x 480."""
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    out = []
    for angle in np.linspace(0, 2 * np.pi, n_views, endpoint=False) + rng.uniform(0, 0.3):
        centre = np.array([4 * np.cos(angle), 4 * np.sin(angle), 1.0])
        forward = -centre / np.linalg.norm(centre)
        right = np.cross(forward, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])
        out.append(K @ np.c_[R, -R @ centre])
    return np.array(out)


def crowded_scene(rng, n_views: int, n_people: int):
    """(P (V, 3, 4), per view a list of (T, 3) detections, the people's (T, 3) targets)."""
    P = cameras(rng, n_views)
    people = [rng.normal([x, rng.uniform(-1, 1), 1.0], 0.3, (N_TARGETS, 3)) for x in rng.uniform(-1.5, 1.5, n_people)]
    views = []
    for v in range(n_views):
        found = []
        for person in people:
            if rng.random() < 0.15:  # this view missed them
                continue
            image = np.c_[person, np.ones(len(person))] @ P[v].T  # (T, 3); NaN behind the camera
            pixels = np.where(image[:, 2:] > 0, image[:, :2] / image[:, 2:], np.nan) + rng.normal(
                0, 1.5, (N_TARGETS, 2)
            )
            confidence = rng.uniform(0.3, 1.0, N_TARGETS) * (rng.random(N_TARGETS) > 0.2)
            detection = np.c_[np.nan_to_num(pixels), confidence]
            found += [detection, detection[rng.permutation(N_TARGETS)]]  # and a mirror of sorts
        if rng.random() < 0.3:  # a false person: a few joints, low confidence
            false = np.c_[rng.uniform(0, 640, (N_TARGETS, 2)), 0.2 * (rng.random(N_TARGETS) < 0.4)]
            found.insert(int(rng.integers(0, len(found) + 1)), false)
        views.append(found)
    return P, views, people
