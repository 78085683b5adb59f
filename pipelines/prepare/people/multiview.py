"""Multi-view triangulation of keypoints: confidence-weighted DLT, a per-frame consensus of views (which views
show the same person) and per-joint rejection of views by reprojection error.

All pixel coordinates here are undistorted (``undistort_points``), so that a camera is its 3x4 projection
``P = K [R | t]``. Errors are measured as a fraction of the image height, so that one threshold fits every camera.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from itertools import combinations

import cv2
import numpy as np

from pipelines.datasets.camera import Camera

#: fewest joints two views must share for a consensus hypothesis
MIN_SHARED_JOINTS = 6


def projection_matrix(camera: Camera) -> np.ndarray:
    """(3, 4) ``K [R | t]`` of an undistorted camera."""
    return camera.K @ camera.cam_from_world[:3]


def undistort_points(camera: Camera, xy: np.ndarray) -> np.ndarray:
    """(..., 2) distorted pixels -> the pixels an undistorted camera with the same K would see (OpenCV model)."""
    flat = np.ascontiguousarray(xy, np.float64).reshape(-1, 1, 2)
    if not np.any(camera.dist) or flat.size == 0:
        return np.asarray(xy, np.float64).copy()
    return cv2.undistortPoints(flat, camera.K, camera.dist, P=camera.K).reshape(np.shape(xy))


def triangulate(P: np.ndarray, xy: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted DLT: the X minimising ``sum_v w_v^2 |x_v P3_v - P1_v, y_v P3_v - P2_v| . X~`` (Hartley & Zisserman
    §12.2), solved by SVD of the stacked rows.

    Args:
        P: (V, 3, 4) projections, or (..., V, 3, 4) a set of them per point. xy: (..., V, 2) pixels.
        weights: (..., V) >= 0 (0 = view not used).

    Returns:
        (..., 3) points; NaN where fewer than two views have weight > 0.
    """
    rows_x = xy[..., 0, None] * P[..., 2, :] - P[..., 0, :]  # (..., V, 4)
    rows_y = xy[..., 1, None] * P[..., 2, :] - P[..., 1, :]
    A = np.concatenate([rows_x, rows_y], axis=-2) * np.concatenate([weights, weights], axis=-1)[..., None]
    scale = np.linalg.norm(A, axis=-1, keepdims=True)
    A = A / np.where(scale > 0, scale, 1)  # row equilibration: DLT is badly conditioned in raw pixels
    enough = (weights > 0).sum(axis=-1) >= 2
    homogeneous = np.zeros((*enough.shape, 4))
    homogeneous[enough] = null_vectors(A[enough])
    with np.errstate(divide="ignore", invalid="ignore"):
        points = homogeneous[..., :3] / homogeneous[..., 3:]
    return np.where(enough[..., None], points, np.nan)


#: squarings of the adjugate in :func:`null_vectors`; k of them raise the error's ratio to the power 2^k
NULL_SQUARINGS = 5
#: a null vector whose eigen-residual |M v - (v.M v) v| / |M| exceeds this is taken from the SVD instead
NULL_RESIDUAL = 1e-10


def null_vectors(A: np.ndarray) -> np.ndarray:
    """The unit right-singular vectors of the smallest singular values of ``A`` (..., R, 4), sign arbitrary: the
    homogeneous least-squares solution of ``A X = 0``, as ``np.linalg.svd(A)[2][..., -1, :]`` gives it.

    The vector is the eigenvector v of M = A^T A (4 x 4) of its smallest eigenvalue. The adjugate
    adj(M) = sum_i (prod_{j != i} lambda_j) v_i v_i^T weighs v_i v_i^T by the product of the other eigenvalues, so
    v v^T leads and each other term is smaller by lambda_min / lambda_i; squaring the matrix ``NULL_SQUARINGS``
    times (each normalised) raises those ratios to the power 2^k, and its largest column is then v. Elementwise
    arithmetic and 4 x 4 products over the batch, several times faster than a LAPACK SVD per system; a vector whose
    residual says it has not converged (two nearly equal smallest eigenvalues, or M = 0) is taken from the SVD, the
    reference (tests/test_consensus.py compares the two).
    """
    M = np.swapaxes(A, -1, -2) @ A
    B = _adjugate4(M)
    for _ in range(NULL_SQUARINGS):
        B = B / np.maximum(np.linalg.norm(B, axis=(-2, -1), keepdims=True), 1e-300)
        B = B @ B
    column = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
    v = np.take_along_axis(B, column[..., None, None], axis=-1)[..., 0]
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    v = v / np.where(norm > 0, norm, 1)
    Mv = (M @ v[..., None])[..., 0]
    residual = np.linalg.norm(Mv - (Mv * v).sum(-1, keepdims=True) * v, axis=-1)
    unsure = ~(residual <= NULL_RESIDUAL * np.linalg.norm(M, axis=(-2, -1))) | (norm[..., 0] == 0)
    if unsure.any():
        v[unsure] = np.linalg.svd(A[unsure])[2][..., -1, :]
    return v


def nanmedian(x: np.ndarray, axis: int) -> np.ndarray:
    """``np.nanmedian(x, axis)``, the same numbers, by one sort (NaNs sort last) and the middle one or two of each
    slice's non-NaN values: numpy's own takes a masked-array path for short slices, which dominated the
    consensus's scoring. All-NaN slices give NaN (without numpy's warning)."""
    ordered = np.sort(x, axis=axis)
    count = np.expand_dims((~np.isnan(x)).sum(axis=axis), axis)
    low = np.take_along_axis(ordered, np.maximum(count - 1, 0) // 2, axis=axis)
    high = np.take_along_axis(ordered, count // 2 - (count == 0), axis=axis)
    return np.squeeze(np.where(count > 0, (low + high) / 2, np.nan), axis=axis)


def _adjugate4(M: np.ndarray) -> np.ndarray:
    """(..., 4, 4) adjugates of ``M`` (..., 4, 4): adj(M)[j, i] = (-1)^(i+j) det(M without row i and column j), each
    3 x 3 minor by the rule of Sarrus (elementwise over the batch)."""
    adjugate = np.empty_like(M)
    for i in range(4):
        for j in range(4):
            minor = np.delete(np.delete(M, i, axis=-2), j, axis=-1)
            adjugate[..., j, i] = (-1) ** (i + j) * _det3(minor)
    return adjugate


def _det3(m: np.ndarray) -> np.ndarray:
    """(...,) determinants of (..., 3, 3) matrices."""
    a, b, c = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    return (
        a * (m[..., 1, 1] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 1])
        - b * (m[..., 1, 0] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 0])
        + c * (m[..., 1, 0] * m[..., 2, 1] - m[..., 1, 1] * m[..., 2, 0])
    )


def project(P: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(V, 3, 4) projections, (..., 3) points -> (..., V, 2) pixels (NaN behind a camera)."""
    homogeneous = np.concatenate([points, np.ones_like(points[..., :1])], axis=-1)
    image = np.einsum("vij,...j->...vi", P, homogeneous)
    depth = image[..., 2:]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(depth > 0, image[..., :2] / depth, np.nan)


def relative_errors(P: np.ndarray, points: np.ndarray, xy: np.ndarray, heights: np.ndarray) -> np.ndarray:
    """(..., V) reprojection error of ``points`` (..., 3) against ``xy`` (..., V, 2), as a fraction of the height."""
    return np.linalg.norm(project(P, points) - xy, axis=-1) / heights


@dataclass
class Consensus:
    """Which detection each view keeps in one frame: ``person[v]`` (index into that view's people, -1: none)."""

    person: list[int]
    error: float


def consensus(
    P: np.ndarray,
    people: list[list[np.ndarray]],
    heights: np.ndarray,
    threshold: float,
    previous=None,
    radius: float = np.inf,
) -> Consensus:
    """The views that see one person, found as RANSAC does over pairs of detections from two views.

    Each pair is triangulated; a view agrees when one of its detections reprojects within ``threshold`` (median
    over the shared joints, fraction of the height). With ``previous`` (the followed person's targets in the last
    kept frame, (T, 3)) only hypotheses within ``radius`` metres of it (median over the joints) count, so that the
    same person is followed through the sequence; among those, the most agreeing views win, then the nearest, then
    the smaller error, then the first pair. A view whose detections all disagree (nobody, or somebody else) keeps
    none; no hypothesis at all gives every view -1. Every pair at once (``PAIRS_AT_ONCE`` at a time);
    :func:`consensus_reference` is the same search one pair at a time.

    Args:
        P: (V, 3, 4). people: per view, a list of (T, 3) detections (x, y, confidence). heights: (V,) pixels.
    """
    candidates = [(v, p) for v, found in enumerate(people) for p in range(len(found))]
    none = Consensus([-1] * len(people), np.inf)
    pairs = np.array(
        [(i, j) for i, j in combinations(range(len(candidates)), 2) if candidates[i][0] != candidates[j][0]]
    )
    if len(pairs) == 0:
        return none
    detections = np.stack([people[v][p] for v, p in candidates])  # (C, T, 3)
    view = np.array([v for v, _ in candidates])
    seen = detections[..., 2] > 0
    pairs = pairs[(seen[pairs[:, 0]] & seen[pairs[:, 1]]).sum(-1) >= MIN_SHARED_JOINTS]
    scored = [_score_pairs(P, detections, view, heights, threshold, chunk, previous) for chunk in _chunks(pairs)]
    if not scored:
        return none
    choice, agreeing, distance, error = (np.concatenate(x) for x in zip(*scored))
    near = np.flatnonzero(~(distance > radius))
    if near.size == 0:
        return none
    best = near[np.lexsort((error[near], distance[near], -agreeing[near]))[0]]
    return Consensus([int(c) for c in choice[best]], float(error[best]))


#: hypotheses scored at once by :func:`consensus` (bounds its arrays: pairs x joints x detections)
PAIRS_AT_ONCE = 512


def _chunks(pairs: np.ndarray) -> list[np.ndarray]:
    return [pairs[a : a + PAIRS_AT_ONCE] for a in range(0, len(pairs), PAIRS_AT_ONCE)]


def _score_pairs(P, detections, view, heights, threshold, pairs, previous):
    """Each pair's hypothesis (:func:`consensus`): per view the chosen detection's index in its view (-1: none),
    (N, V); the agreeing views (N,); the median distance to ``previous`` (N,; 0 without one, inf if unknown); the
    mean error of the chosen detections (N,; inf if none)."""
    n_views, n, rows = len(P), len(pairs), np.arange(len(pairs))
    first, second = pairs[:, 0], pairs[:, 1]
    shared = (detections[first, :, 2] > 0) & (detections[second, :, 2] > 0)
    # the two views' rows of triangulate's DLT only: the other views' rows are zero
    xy = np.stack([detections[first, :, :2], detections[second, :, :2]], axis=2)  # (N, T, 2, 2)
    weights = np.stack([detections[first, :, 2], detections[second, :, 2]], axis=2) * shared[..., None]
    pair_P = np.stack([P[view[first]], P[view[second]]], axis=1)[:, None]  # (N, 1, 2, 3, 4)
    points = triangulate(pair_P, xy, weights)  # (N, T, 3)
    pixels = project(P, points)[:, :, view]  # (N, T, C, 2)
    gap = np.linalg.norm(pixels - detections[None, ..., :2].transpose(0, 2, 1, 3), axis=-1)  # (N, T, C)
    used = (detections[..., 2] > 0).T[None] & np.isfinite(points).all(-1)[..., None]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices: no joint seen
        error = nanmedian(np.where(used, gap, np.nan), axis=1) / heights[view]  # (N, C)
        behind = (used & np.isnan(gap)).any(1)  # a joint behind the camera: the median is NaN, never chosen
        error = np.where(behind | (used.sum(1) < MIN_SHARED_JOINTS // 2), np.inf, error)
        distance = np.zeros(n) if previous is None else nanmedian(np.linalg.norm(points - previous, axis=-1), -1)
    choice, best = np.full((n, n_views), -1), np.full((n, n_views), np.inf)
    for v in range(n_views):
        mine = np.flatnonzero(view == v)
        if mine.size:
            index = np.argmin(error[:, mine], axis=1)  # the first of equals, as the reference's strict <
            lowest = error[rows, mine[index]]
            choice[:, v] = np.where(lowest < threshold, index, -1)
            best[:, v] = np.where(lowest < threshold, lowest, np.inf)
    agreeing = (choice >= 0).sum(1)
    chosen = np.where(choice >= 0, best, 0.0).sum(1)
    mean = np.where(agreeing > 0, chosen / np.maximum(agreeing, 1), np.inf)
    return choice, agreeing, np.nan_to_num(distance, nan=np.inf), mean


def consensus_reference(
    P: np.ndarray,
    people: list[list[np.ndarray]],
    heights: np.ndarray,
    threshold: float,
    previous=None,
    radius: float = np.inf,
) -> Consensus:
    """:func:`consensus` one hypothesis at a time, as the docstring there says it: the slow reference of the
    vectorised search (tests/test_prepare_people.py). The views that see one person, found as RANSAC does over
    pairs of detections from two views.

    Each pair is triangulated; a view agrees when one of its detections reprojects within ``threshold`` (median
    over the shared joints, fraction of the height). With ``previous`` (the followed person's targets in the last
    kept frame, (T, 3)) only hypotheses within ``radius`` metres of it (median over the joints) count, so that the
    same person is followed through the sequence; among those, the most agreeing views win, then the nearest, then
    the smaller error. A view whose detections all disagree (nobody, or somebody else) keeps none; no hypothesis
    at all gives every view -1.

    Args:
        P: (V, 3, 4). people: per view, a list of (T, 3) detections (x, y, confidence). heights: (V,) pixels.
    """
    candidates = [(v, p) for v, found in enumerate(people) for p in range(len(found))]
    best, best_key = Consensus([-1] * len(people), np.inf), None
    for (v1, p1), (v2, p2) in combinations(candidates, 2):
        if v1 == v2:
            continue
        a, b = people[v1][p1], people[v2][p2]
        shared = (a[:, 2] > 0) & (b[:, 2] > 0)
        if shared.sum() < MIN_SHARED_JOINTS:
            continue
        xy = np.zeros((len(a), len(people), 2))
        weights = np.zeros((len(a), len(people)))
        xy[:, v1], xy[:, v2] = a[:, :2], b[:, :2]
        weights[:, v1], weights[:, v2] = a[:, 2] * shared, b[:, 2] * shared
        points = triangulate(P, xy, weights)
        choice, errors = _agreeing(P, people, heights, points, threshold)
        agreeing = sum(c >= 0 for c in choice)
        distance = 0.0 if previous is None else float(np.nanmedian(np.linalg.norm(points - previous, axis=-1)))
        distance = np.nan_to_num(distance, nan=np.inf)
        if distance > radius:
            continue
        key = (-agreeing, distance, float(np.mean(errors)) if errors else np.inf)
        if best_key is None or key < best_key:
            best, best_key = Consensus(choice, key[2]), key
    return best


def _agreeing(P, people, heights, points, threshold) -> tuple[list[int], list[float]]:
    choice, errors = [], []
    for v, found in enumerate(people):
        best, best_error = -1, threshold
        for p, detection in enumerate(found):
            seen = (detection[:, 2] > 0) & np.isfinite(points).all(axis=-1)
            if seen.sum() < MIN_SHARED_JOINTS // 2:
                continue
            error = np.linalg.norm(project(P[v : v + 1], points[seen])[:, 0] - detection[seen, :2], axis=-1)
            error = float(np.median(error)) / heights[v]
            if error < best_error:
                best, best_error = p, error
        choice.append(best)
        if best >= 0:
            errors.append(best_error)
    return choice, errors


def triangulate_robust(
    P: np.ndarray, xy: np.ndarray, confidence: np.ndarray, heights: np.ndarray, threshold: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per-joint triangulation that drops the worst view while its error exceeds ``threshold`` and > 2 remain.

    Args:
        P: (V, 3, 4). xy: (..., V, 2). confidence: (..., V) (0 = not seen). heights: (V,).

    Returns:
        points (..., 3) (NaN where under two views remain) and the weights used (..., V).
    """
    weights = confidence.astype(np.float64).copy()
    for _ in range(P.shape[0]):
        points = triangulate(P, xy, weights)
        errors = np.where(weights > 0, relative_errors(P, points, xy, heights), -np.inf)
        worst = np.nanargmax(np.where(np.isnan(errors), np.inf, errors), axis=-1)
        worst_error = np.take_along_axis(errors, worst[..., None], axis=-1)[..., 0]
        drop = (worst_error > threshold) & ((weights > 0).sum(axis=-1) > 2)
        if not drop.any():
            break
        np.put_along_axis(
            weights,
            worst[..., None],
            np.where(drop[..., None], 0.0, np.take_along_axis(weights, worst[..., None], -1)),
            -1,
        )
    points = triangulate(P, xy, weights)
    errors = relative_errors(P, points, xy, heights)
    bad = ~np.all(np.where(weights > 0, errors <= threshold, True), axis=-1)  # two views that disagree
    return np.where(bad[..., None], np.nan, points), np.where(bad[..., None], 0.0, weights)
