"""From per-view people to one person's 3D targets per frame: the consensus of views, then robust triangulation.
Frames where fewer than two views agree on a person, or the torso cannot be placed, are dropped with a reason.

A detector may swap one pair of limbs alone, the legs as they cross or the arms as they fold, in a view where the
rest of the person is right: each view's legs and arms are exchanged left for right where the exchange agrees with the
other views and the detection as given does not (:func:`side_swaps`), before the triangulation."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipelines.datasets.camera import Camera
from pipelines.datasets.keypoints import TARGET_NAMES, TARGETS, mirror_index
from pipelines.prepare.people.multiview import (
    consensus,
    project,
    projection_matrix,
    relative_errors,
    triangulate_robust,
    undistort_points,
)
from pipelines.prepare.people.tracks import (
    TRACK_RADIUS,
    Track,
    link_tracks,
    matches,
    orient_sides,
    people_in_frame,
    reach,
)

#: least detector confidence of a keypoint that is used
MIN_CONFIDENCE = 0.3
#: fewest targets a kept frame has triangulated
MIN_TARGETS = 8
#: the left targets of each limb a detector swaps alone (the hips and shoulders stay with the torso)
SWAPPED_LIMBS = (("l_knee", "l_ankle", "l_foot"), ("l_elbow", "l_wrist"))


@dataclass
class Triangulated:
    """One person per kept frame.

    Attributes:
        frames: kept source frame indices (ascending).
        points: (F, T, 3) triangulated targets (NaN: not triangulated).
        keypoints: (F, V, T, 3) undistorted pixels and confidence of the chosen person (0 where not used), each
            view's swapped limbs put right (:func:`side_swaps`).
        used: (F, V) bool, the views that agreed on the person.
        distorted: (F, V, T, 3) the chosen person's keypoints as detected (for drawing), limbs put right.
        detected: (F, V, T, 3) undistorted, with the detector's confidence: the chosen person, or in a view that
            disagreed the detection nearest to the triangulated one (the report measures every camera on it).
        dropped: source frame -> reason.
        view_notes: per view, counts of views with nobody seen, views showing somebody else (another person the
            views agree on), views that disagreed, and views left out since other people overlapped the person
            (``pipelines.prepare.people.occlusion``; counted by the caller).
        others: source frame -> the other people's (T, 3) targets in it (``triangulate_people``'s ``others``).
    """

    frames: list[int]
    points: np.ndarray
    keypoints: np.ndarray
    used: np.ndarray
    distorted: np.ndarray
    detected: np.ndarray
    dropped: dict[int, str]
    view_notes: list[dict[str, int]]
    others: dict[int, list[np.ndarray]] = field(default_factory=dict)


def _undistorted_people(cameras: list[Camera], people: list[list[np.ndarray]]) -> list[list[np.ndarray]]:
    out = []
    for camera, found in zip(cameras, people):
        converted = []
        for person in found:
            person = person.copy()
            person[:, 2] = np.where(person[:, 2] >= MIN_CONFIDENCE, person[:, 2], 0.0)
            person[:, :2] = undistort_points(camera, person[:, :2])
            converted.append(person)
        out.append(converted)
    return out


def _with_mirrored(found: list[np.ndarray]) -> list[np.ndarray]:
    """The detections and their left/right mirrors: detectors swap the sides of a person seen from the back."""
    order = [mirror_index(t) for t in range(len(TARGETS))]
    return list(found) + [person[order] for person in found]


def _nearest(P, undistorted, person, chosen, xyz) -> np.ndarray:
    """(V, T, 3): the chosen detections, and in views without one the detection nearest to ``xyz``."""
    out = chosen.copy()
    seen = np.isfinite(xyz).all(-1)
    for v, found in enumerate(undistorted):
        if person[v] >= 0 or not found:
            continue
        errors = [
            np.nanmedian(np.linalg.norm(project(P[0][v : v + 1], xyz[seen])[:, 0] - d[seen, :2], axis=-1))
            for d in found
        ]
        out[v] = found[int(np.nanargmin(errors))] if np.isfinite(errors).any() else found[0]
    return out


def find_tracks(cameras: list[Camera], people, frames: list[int], threshold: float) -> list[Track]:
    """Every person the views agree on in ``frames``, linked into tracks whose sides hold over time
    (``pipelines.prepare.people.tracks``, ``orient_sides``); ``people`` and ``threshold`` as
    :func:`triangulate_people`'s."""
    P = np.stack([projection_matrix(c) for c in cameras])
    heights = np.array([c.height for c in cameras], np.float64)
    per_frame = {}
    for frame in frames:
        undistorted = _undistorted_people(cameras, [_with_mirrored(people[v].get(frame, [])) for v in range(len(P))])
        found = people_in_frame(P, undistorted, heights, threshold)
        per_frame[frame] = [
            (xyz, sum(p >= 0 for p in person), _side_votes(undistorted, person)) for xyz, person in found
        ]
    return [orient_sides(track) for track in link_tracks(per_frame)]


def _side_votes(undistorted: list[list[np.ndarray]], person: list[int]) -> int:
    """The agreeing views whose detection was taken as labelled minus those taken mirrored (each view's list holds
    its detections, then their mirrors: ``_with_mirrored``)."""
    return sum(1 if p < len(found) // 2 else -1 for found, p in zip(undistorted, person) if p >= 0)


def triangulate_people(
    cameras: list[Camera], people, frames: list[int], threshold: float, route=None, others=None
) -> Triangulated:
    """Consensus and triangulation of every frame (module docstring).

    Args:
        people: ``people[v][frame]`` lists of (T, 3) targets (distorted pixels). frames: source frames to use.
        threshold: reprojection error (fraction of the image height) beyond which a view disagrees.
        route: the followed person's targets by frame (``pipelines.prepare.people.tracks.guide``): each frame keeps the
            person within ``TRACK_RADIUS`` of them, and a frame without them is dropped. None: the person is followed
            from the first frame two views agree on, within ``pipelines.prepare.people.tracks.reach``.
        others: the other people's targets by frame (lists of (T, 3)): a view that shows one of them is counted as
            showing somebody else, not as disagreeing.
    """
    P = np.stack([projection_matrix(c) for c in cameras])
    heights = np.array([c.height for c in cameras], np.float64)
    others = others or {}
    n_views, n_targets = len(cameras), len(TARGETS)
    kept, points, keypoints, used, distorted, detected, dropped = [], [], [], [], [], [], {}
    notes = [{"no_person": 0, "other_person": 0, "disagreed": 0, "overlapped": 0} for _ in cameras]
    previous, previous_frame = None, 0
    for frame in frames:
        raw = [_with_mirrored(people[v].get(frame, [])) for v in range(n_views)]
        undistorted = _undistorted_people(cameras, raw)
        if route is not None and frame not in route:
            dropped[frame] = "the person followed is not seen by two agreeing views near this frame"
            continue
        if route is not None:
            previous, radius = route[frame], TRACK_RADIUS
        else:
            radius = reach(frame - previous_frame) if previous is not None else np.inf
        choice = consensus(P, undistorted, heights, threshold, previous, radius)
        for v in range(n_views):
            if choice.person[v] < 0:
                notes[v][_why_not(P[v], undistorted[v], others.get(frame, []), heights[v], threshold)] += 1
        frame_xy = np.zeros((n_views, n_targets, 3))
        frame_raw = np.zeros((n_views, n_targets, 3))
        for v, p in enumerate(choice.person):
            if p >= 0:
                frame_xy[v], frame_raw[v] = undistorted[v][p], raw[v][p]
        if sum(p >= 0 for p in choice.person) < 2:
            followed = " (the person followed so far)" if previous is not None else ""
            dropped[frame] = f"fewer than two views agree on a person{followed}"
            continue
        for v, order in enumerate(side_swaps(P, frame_xy, heights, threshold)):
            frame_xy[v], frame_raw[v] = frame_xy[v, order], frame_raw[v, order]
        xyz, weights = triangulate_robust(
            P, frame_xy[..., :2].transpose(1, 0, 2), frame_xy[..., 2].T, heights, threshold
        )
        if np.isfinite(xyz).all(-1).sum() < MIN_TARGETS:
            dropped[frame] = f"fewer than {MIN_TARGETS} joints triangulated"
            continue
        detected.append(_nearest(P[None], undistorted, choice.person, frame_xy, xyz))
        frame_xy[..., 2] = weights.T * (frame_xy[..., 2] > 0)
        kept.append(frame)
        points.append(xyz)
        keypoints.append(frame_xy)
        used.append(np.array(choice.person) >= 0)
        distorted.append(frame_raw)
        previous, previous_frame = xyz, frame
    shape = (-1, n_views, n_targets, 3)
    return Triangulated(
        kept,
        np.array(points).reshape(-1, n_targets, 3),
        np.array(keypoints).reshape(shape),
        np.array(used, bool).reshape(-1, n_views),
        np.array(distorted).reshape(shape),
        np.array(detected).reshape(shape),
        dropped,
        notes,
        {f: others[f] for f in kept if others.get(f)},
    )


def side_swaps(P: np.ndarray, xy: np.ndarray, heights: np.ndarray, threshold: float) -> np.ndarray:
    """(V, T) orders of the targets that undo, view by view, a limb's left/right swap (``SWAPPED_LIMBS``).

    A view's limb pair is exchanged where, against the others' robust triangulation (:func:`triangulate_robust`
    over every other view, the views corrected so far as corrected), the limb's median reprojection error as
    detected exceeds ``threshold`` and the exchanged one's does not. Views are taken in order, so two views that
    swapped the same limb are both found as long as two others agree.

    Args:
        P: (V, 3, 4). xy: (V, T, 3) undistorted pixels and confidence (0: not seen). heights: (V,).
        threshold: reprojection error (fraction of the height) beyond which a view disagrees.
    """
    n_views, n_targets = xy.shape[:2]
    orders = np.tile(np.arange(n_targets), (n_views, 1))
    pairs = [[TARGET_NAMES.index(side + n[1:]) for side in "lr" for n in names] for names in SWAPPED_LIMBS]
    for v in range(n_views):
        rest = [u for u in range(n_views) if u != v and (xy[u, :, 2] > 0).any()]
        if len(rest) < 2 or not (xy[v, :, 2] > 0).any():
            continue
        seen = np.stack([xy[u, orders[u]] for u in rest])
        points, _ = triangulate_robust(
            P[rest], seen[..., :2].transpose(1, 0, 2), seen[..., 2].T, heights[rest], threshold
        )
        for pair in pairs:
            swapped = [mirror_index(t) for t in pair]
            as_detected = _limb_error(P[v], points[pair], xy[v, pair], heights[v])
            exchanged = _limb_error(P[v], points[pair], xy[v, swapped], heights[v])
            if as_detected > threshold >= exchanged:
                orders[v, pair] = swapped
    return orders


def _limb_error(P_v: np.ndarray, points: np.ndarray, xy: np.ndarray, height: float) -> float:
    """Median reprojection error (fraction of ``height``) of (N, 3) ``points`` against (N, 3) ``xy`` (pixels and
    confidence), over the targets seen and triangulated; inf when none is."""
    seen = (xy[:, 2] > 0) & np.isfinite(points).all(-1)
    if not seen.any():
        return np.inf
    return float(np.median(relative_errors(P_v[None], points[seen], xy[seen, None, :2], np.array([height]))))


def _why_not(P_v, detections, others, height, threshold) -> str:
    """Why a view kept no detection of the followed person: nobody seen, somebody else (a detection that shows one
    of ``others``), or a disagreement."""
    if not detections:
        return "no_person"
    if any(matches(P_v, d, o, height, threshold) for d in detections for o in others):
        return "other_person"
    return "disagreed"
