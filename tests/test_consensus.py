"""The consensus of views (pipelines/prepare/multiview.py) scores every pair of detections at once; its slow
reference, ``consensus_reference``, scores one pair at a time. On random scenes with several people, mirrored
detections, missing joints, a false person, points behind a camera and a previous position to stay near, both
choose the same detections."""

import numpy as np
import pytest

from pipelines.prepare import multiview
from pipelines.prepare.multiview import consensus, consensus_reference, project
from pipelines.synthetic.crowd import HEIGHT, N_TARGETS, cameras, crowded_scene


@pytest.mark.parametrize("seed", range(12))
def test_every_pair_at_once_chooses_as_one_pair_at_a_time(seed, monkeypatch):
    rng = np.random.default_rng(seed)
    P, views, people = crowded_scene(rng, int(rng.integers(2, 7)), int(rng.integers(1, 4)))
    heights = np.full(len(P), HEIGHT)
    previous = people[0] + rng.normal(0, 0.05, people[0].shape) if seed % 2 else None
    radius = 0.5 if seed % 2 else np.inf
    if seed % 3 == 0:
        monkeypatch.setattr(multiview, "PAIRS_AT_ONCE", 7)  # several chunks
    for threshold in (0.01, 0.05):
        fast = consensus(P, views, heights, threshold, previous, radius)
        slow = consensus_reference(P, views, heights, threshold, previous, radius)
        assert fast.person == slow.person
        # the mean error of the same detections, summed in another order: float64 rounding only
        assert fast.error == pytest.approx(slow.error, rel=1e-12)


def test_nobody_and_one_view_give_no_hypothesis():
    P = cameras(np.random.default_rng(0), 3)
    heights = np.full(3, HEIGHT)
    assert consensus(P, [[], [], []], heights, 0.05).person == [-1, -1, -1]
    lonely = [[np.c_[np.full((N_TARGETS, 2), 100.0), np.ones(N_TARGETS)]], [], []]
    assert consensus(P, lonely, heights, 0.05).person == [-1, -1, -1]


def _exact_views(P, person, views):
    return [np.c_[project(P[v : v + 1], person)[:, 0], np.ones(N_TARGETS)] for v in views]


def test_a_view_with_too_few_joints_or_joints_behind_it_does_not_agree():
    rng = np.random.default_rng(3)
    P = cameras(rng, 4)
    heights = np.full(4, HEIGHT)
    person = rng.normal([0, 0, 1.0], 0.3, (N_TARGETS, 3))
    first, second, third = _exact_views(P, person, (1, 2, 3))
    few = _exact_views(P, person, (0,))[0]
    few[2:, 2] = 0  # two joints: under MIN_SHARED_JOINTS // 2, not a judge of the hypothesis
    result = consensus(P, [[few], [first], [second], [third]], heights, 0.02)
    assert result.person == [-1, 0, 0, 0]
    assert consensus_reference(P, [[few], [first], [second], [third]], heights, 0.02).person == result.person
    # camera 0 moved into the person: its confident joints behind it make its error NaN, so it does not agree,
    # however well the joints in front of it match
    centre = person.mean(0)
    R = P[0][:, :3]
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    rotation = np.linalg.inv(K) @ R
    inside = P.copy()
    inside[0] = K @ np.c_[rotation, -rotation @ centre]
    depth = (rotation @ (person - centre).T)[2]
    assert (depth < 0).sum() >= 3 and (depth > 0).sum() >= 6
    front = np.c_[np.nan_to_num(project(inside[0:1], person)[:, 0]), np.ones(N_TARGETS)]
    views = [[front], [first], [second], [third]]
    for search in (consensus, consensus_reference):
        assert search(inside, views, heights, 0.02).person == [-1, 0, 0, 0]
