"""The consensus of views (pipelines/prepare/people/multiview.py) scores every pair of detections at once; its slow
reference, ``consensus_reference``, scores one pair at a time. On random scenes with several people, mirrored
detections, missing joints, a false person, points behind a camera and a previous position to stay near, both
choose the same detections."""

import warnings

import numpy as np
import pytest

from pipelines.prepare.people import multiview
from pipelines.prepare.people.multiview import consensus, consensus_reference, project
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


def _dlt_rows(rng, n, views, noise):
    """(n, 2 * views, 4) equilibrated DLT rows of random points seen by random cameras, ``noise`` pixels off."""
    P = cameras(rng, views)
    X = rng.normal([0, 0, 1.0], 0.3, (n, 3))
    xy = np.stack([project(P[v : v + 1], X)[:, 0] for v in range(views)], axis=1) + rng.normal(0, noise, (n, views, 2))
    rows = np.concatenate([xy[..., :1] * P[:, 2] - P[:, 0], xy[..., 1:] * P[:, 2] - P[:, 1]], axis=1)
    return rows / np.linalg.norm(rows, axis=-1, keepdims=True), X


def test_the_adjugate_is_the_determinant_times_the_inverse():
    """``_adjugate4`` against numpy: adj(M) = det(M) M^-1 for invertible M (float64; each entry is about 40 products
    of entries of size 1, so agreement to 1e-12 of the largest entry)."""
    M = np.random.default_rng(0).normal(size=(200, 4, 4))
    expected = np.linalg.det(M)[:, None, None] * np.linalg.inv(M)
    assert np.abs(multiview._adjugate4(M) - expected).max() <= 1e-12 * np.abs(expected).max()


@pytest.mark.parametrize("case", ["two views, noisy", "six views, noisy", "exact", "inconsistent", "degenerate"])
def test_null_vectors_are_the_svds(case):
    """``null_vectors`` against numpy's SVD, the reference: the last right-singular vector up to its sign. Where the
    smallest singular value is well apart from the next (every case but the last two), the angle between the two is
    bounded by the residual the fast path accepts (1e-10 of |M|) over that gap (Davis-Kahan), so 1e-9; in the others
    the vector is the SVD's own (the fast path's residual check hands them over) or an equally good one, so its
    Rayleigh quotient is the smallest eigenvalue of A^T A to 1e-9 of |M|."""
    rng = np.random.default_rng(7)
    if case == "inconsistent":
        A = rng.normal(size=(500, 4, 4))
    elif case == "degenerate":  # two equal smallest singular values: any vector of their plane is a solution
        Q = np.linalg.qr(rng.normal(size=(500, 4, 4)))[0]
        A = Q * np.array([1.0, 0.5, 1e-3, 1e-3])[None, None, :] @ np.swapaxes(Q, -1, -2)
    else:
        views, noise = {"two views, noisy": (2, 1.0), "six views, noisy": (6, 2.0), "exact": (3, 0.0)}[case]
        A, _ = _dlt_rows(rng, 500, views, noise)
    fast, reference = multiview.null_vectors(A), np.linalg.svd(A)[2][..., -1, :]
    assert np.allclose(np.linalg.norm(fast, axis=-1), 1, atol=1e-12)
    M = np.swapaxes(A, -1, -2) @ A
    quotient = np.einsum("ni,nij,nj->n", fast, M, fast)
    smallest = np.linalg.svd(A, compute_uv=False)[:, -1] ** 2
    assert np.abs(quotient - smallest).max() <= 1e-9 * np.linalg.norm(M, axis=(-2, -1)).max()
    if case not in ("inconsistent", "degenerate"):
        assert np.abs(1 - np.abs((fast * reference).sum(-1))).max() <= 1e-9


def test_triangulation_of_exact_views_is_the_point():
    rng = np.random.default_rng(2)
    P = cameras(rng, 4)
    X = rng.normal([0, 0, 1.0], 0.3, (50, 3))
    xy = np.stack([project(P[v : v + 1], X)[:, 0] for v in range(4)], axis=1)
    weights = np.ones((50, 4))
    weights[0, 1:] = 0  # one view: no point
    points = multiview.triangulate(P, xy, weights)
    assert np.isnan(points[0]).all()
    # float64 DLT of exact pixels: 1e-9 m, far above rounding (1e-12) and far below any pixel's worth (1e-4)
    assert np.abs(points[1:] - X[1:]).max() < 1e-9


def test_nanmedian_is_numpys():
    """The consensus's median is numpy's ``nanmedian`` to the bit, with NaNs, infinities and all-NaN slices."""
    rng = np.random.default_rng(4)
    x = rng.normal(size=(40, 9, 7))
    x[rng.random(x.shape) < 0.4] = np.nan
    x[0] = np.nan
    x[1, :3] = np.inf
    x[2, :, 0] = -np.inf
    for axis in (0, 1, -1):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # numpy's all-NaN slice warning
            expected = np.nanmedian(x, axis=axis)
        assert np.array_equal(multiview.nanmedian(x, axis), expected, equal_nan=True)
