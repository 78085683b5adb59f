"""Cameras in step (docs/guides/real-captures.md, *Cameras in step*): each camera's time offset, estimated from the
keypoints, and the whole-frame part of it corrected by renumbering that camera's frames.

Camera c's offset d (frames) says that its frame t shows the instant of the other cameras' frame t + d: a camera
started k frames late has d = +k. For each candidate d the other cameras' keypoints of frame t + d are triangulated
(confidence-weighted DLT, ``pipelines.prepare.multiview``), projected into camera c and compared with c's own
keypoints of frame t; the score is the median error over every joint and frame, as a fraction of the image height.
The best whole d is then refined below a frame on a grid of tenths, the others' points interpolated linearly in time.
Pose2Sim's synchronisation answers the same question with the correlation of the joints' speeds; reprojection needs no
motion in one direction and uses the calibration we already trust.

Each view's person is its most confident detection (summed confidence): one person in view, or the one nearest the
cameras, dominates.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np

from pipelines.datasets.errors import CaptureError
from pipelines.datasets.keypoints import TARGETS, mirror_index
from pipelines.prepare.multiview import projection_matrix, relative_errors, triangulate_robust, undistort_points

#: frames searched each way
MAX_OFFSET = 10
#: fewest (frame, joint) pairs an offset must be scored on
MIN_PAIRS = 30
#: keypoints below this confidence take no part
MIN_CONFIDENCE = 0.3
#: a view whose keypoint reprojects further than this (fraction of the height) leaves that joint's triangulation
TRIANGULATION_ERROR = 0.03
#: the least share of its error that a shift must take off a camera to be made: below it, the minimum is the noise
#: of the keypoints (a shift of every camera alike changes nothing, and small ones would wander)
MIN_GAIN = 0.1
#: each target's left/right counterpart
MIRRORED = [mirror_index(t) for t in range(len(TARGETS))]


def _keypoints(cameras, frames, people) -> tuple[list[int], np.ndarray]:
    """The frames any camera read and (V, N, T, 3) undistorted keypoints with confidence (0: not seen) of each view's
    most confident person."""
    timeline = sorted(set().union(*map(set, frames)))
    out = np.zeros((len(cameras), len(timeline), len(TARGETS), 3))
    for v, camera in enumerate(cameras):
        for n, frame in enumerate(timeline):
            found = people[v].get(frame) or []
            if not found:
                continue
            person = max(found, key=lambda p: float(np.nansum(p[:, 2]))).astype(np.float64).copy()
            person[:, 2] = np.where(person[:, 2] >= MIN_CONFIDENCE, person[:, 2], 0.0)
            person[:, :2] = undistort_points(camera, person[:, :2])
            out[v, n] = np.nan_to_num(person)
    return timeline, out


def _score(P, heights, points: np.ndarray, target: np.ndarray, v: int) -> tuple[float, int]:
    """Median error (fraction of camera v's height) of ``points`` (N, T, 3) projected into v against ``target``
    (N, T, 3) with confidence, and the number of pairs scored. Each frame's detection is taken as it is or with left
    and right swapped, whichever lies nearer: detectors swap the sides of a person seen from the back."""

    def errors_of(keypoints: np.ndarray) -> np.ndarray:
        errors = relative_errors(P[v : v + 1], points, keypoints[..., None, :2], heights[v : v + 1])[..., 0]
        return np.where((keypoints[..., 2] > 0) & np.isfinite(errors), errors, np.nan)

    plain, swapped = errors_of(target), errors_of(target[:, MIRRORED])
    with warnings.catch_warnings():  # frames with no scored joint give an all-NaN median
        warnings.simplefilter("ignore", RuntimeWarning)
        use_swapped = np.nanmedian(swapped, axis=1) < np.nanmedian(plain, axis=1)
    errors = np.where(use_swapped[:, None], swapped, plain)
    usable = np.isfinite(errors)
    return (float(np.median(errors[usable])) if usable.sum() >= MIN_PAIRS else np.inf), int(usable.sum())


def _shifted(points: np.ndarray, d: float) -> np.ndarray:
    """``points`` (N, T, 3) at times n + d (linear between frames; NaN outside the timeline)."""
    n = points.shape[0]
    low = int(np.floor(d))
    a = d - low
    out = np.full_like(points, np.nan)
    for i in range(n):
        j = i + low
        if 0 <= j < n and (a == 0 or j + 1 < n):
            out[i] = points[j] if a == 0 else (1 - a) * points[j] + a * points[j + 1]
    return out


def estimate_offsets(cameras, frames, people, max_offset: int = MAX_OFFSET) -> dict[str, dict]:
    """Per camera: ``offset_frames`` (below a frame), ``error_in_step_pct`` and ``error_at_offset_pct`` (median
    reprojection of the others' triangulation, % of the height) and ``pairs``; a camera that cannot be scored (fewer
    than three cameras, too few joints seen) gets offset 0 and a ``note``. Offsets are in frames of the timeline read
    (every ``stride``-th source frame)."""
    timeline, keypoints = _keypoints(cameras, frames, people)
    P = np.stack([projection_matrix(c) for c in cameras])
    heights = np.array([c.height for c in cameras], np.float64)
    result = {}
    for v, camera in enumerate(cameras):
        others = [o for o in range(len(cameras)) if o != v]
        if len(others) < 2:
            result[camera.name] = {"offset_frames": 0.0, "note": "fewer than three cameras: not estimated"}
            continue
        xy = keypoints[others].transpose(1, 2, 0, 3)  # (N, T, V-1, 3)
        points, _ = triangulate_robust(P[others], xy[..., :2], xy[..., 2], heights[others], TRIANGULATION_ERROR)
        offsets = range(-max_offset, max_offset + 1)
        scores = {d: _score(P, heights, _shifted(points, d), keypoints[v], v) for d in offsets}
        best = min(scores, key=lambda d: scores[d][0])
        if not np.isfinite(scores[best][0]):
            result[camera.name] = {"offset_frames": 0.0, "note": "too few joints seen by it and two others"}
            continue
        tenths = [round(best + k / 10, 1) for k in range(-9, 10)]
        fine = {d: _score(P, heights, _shifted(points, d), keypoints[v], v)[0] for d in tenths}
        offset = min(fine, key=fine.get)
        result[camera.name] = {
            "offset_frames": float(offset),
            "error_in_step_pct": 100 * scores[0][0],
            "error_at_offset_pct": 100 * fine[offset],
            "pairs": scores[best][1],
        }
    return result


#: ``--sync`` words: estimate and apply, estimate and report only, neither
MODES = ("auto", "report", "off")


def parse_sync(text: str) -> str | dict[str, int]:
    """``--sync``: ``auto``, ``report``, ``off`` or ``CAM=OFFSET,...`` (whole frames, a camera's frame t showing the
    others' t + OFFSET); raises ValueError naming what is wrong."""
    if text in MODES:
        return text
    given = {}
    for item in text.split(","):
        name, _, value = item.partition("=")
        try:
            given[name.strip()] = int(value)
        except ValueError:
            raise ValueError(f"--sync: expected auto, report, off or CAM=FRAMES,..., got {item!r}") from None
        if not name.strip():
            raise ValueError(f"--sync: expected auto, report, off or CAM=FRAMES,..., got {item!r}")
    return given


def shift_camera(seen, folder, v: int, shift: int, stride: int):
    """Camera v's frames renumbered from source frame f to f + shift * stride: its observations and its files under
    ``folder`` (``<camera>/<frame>.jpg``, ``mask_raw/<camera>/<frame>.png``), moved in an order that never
    overwrites one not yet moved. Returns ``seen`` with the new numbering."""
    if shift == 0:
        return seen
    step = shift * stride
    name = seen.cameras[v].name
    order = sorted(seen.frames[v], reverse=step > 0)
    for frame in order:
        for sub, suffix in ((folder / name, "jpg"), (folder / "mask_raw" / name, "png")):
            (sub / f"{frame:06d}.{suffix}").replace(sub / f"{frame + step:06d}.{suffix}")
    frames = list(seen.frames)
    people = list(seen.people)
    frames[v] = [f + step for f in seen.frames[v]]
    people[v] = {f + step: found for f, found in seen.people[v].items()}
    return replace(seen, frames=frames, people=people)


def synchronise(seen, folder, sync: str | dict[str, int], stride: int = 1):
    """Estimate every camera's offset (unless ``sync`` is ``off``), apply the whole frames (``auto``: the estimates
    rounded; a dict: the user's, by camera name; ``report``: none), and return ``seen`` renumbered with
    ``seen.sync`` its record.

    ``auto`` shifts one camera at a time, the one whose shift lowers its error most (by ``MIN_GAIN`` of it at least),
    then estimates again: a camera that is out of step spoils the triangulation that every other camera is judged
    by, so the others' first estimates are not to be trusted until it is put right. The record gives, per camera,
    ``offset_frames`` (the frames shifted plus what is left, below a frame), ``applied_frames``, the median error as
    recorded (``error_as_recorded_pct``), in step after the shifts (``error_in_step_pct``) and at the estimate
    (``error_at_offset_pct``)."""
    names = [c.name for c in seen.cameras]
    if isinstance(sync, dict):
        unknown = sorted(set(sync) - set(names))
        if unknown:
            raise CaptureError(f"--sync: {', '.join(unknown)} not among the cameras {names}")
    applied = {n: (sync.get(n, 0) if isinstance(sync, dict) else 0) for n in names}
    for v, name in enumerate(names):
        seen = shift_camera(seen, folder, v, applied[name], stride)
    if sync == "off":
        return replace(seen, sync={"mode": "off", "cameras": {n: {"applied_frames": 0} for n in names}})
    first = estimates = estimate_offsets(seen.cameras, seen.frames, seen.people)
    for _ in range(len(names) if sync == "auto" else 0):
        gains = {
            n: 1 - e["error_at_offset_pct"] / e["error_in_step_pct"]
            for n, e in estimates.items()
            if "error_at_offset_pct" in e and round(e["offset_frames"]) != 0
        }
        gains = {n: gain for n, gain in gains.items() if gain >= MIN_GAIN}
        if not gains:
            break
        name = max(gains, key=gains.get)
        shift = int(round(estimates[name]["offset_frames"]))
        seen = shift_camera(seen, folder, names.index(name), shift, stride)
        applied[name] += shift
        estimates = estimate_offsets(seen.cameras, seen.frames, seen.people)
    record = {}
    for name in names:
        entry = dict(estimates[name])
        entry["offset_frames"] = applied[name] + entry.get("offset_frames", 0.0)
        entry["applied_frames"] = applied[name]
        if "error_in_step_pct" in first[name]:
            entry["error_as_recorded_pct"] = first[name]["error_in_step_pct"]
        record[name] = entry
    return replace(seen, sync={"mode": sync if isinstance(sync, str) else "given", "cameras": record})


def report_followed(seen, found):
    """``seen`` with its ``report``-mode estimates made again on the followed person alone (``found``: the
    ``pipelines.prepare.person_targets.Triangulated`` person, in the views that agreed on them): with other people
    in view, each view's most confident detection, which the first estimate takes, may be somebody else. Other modes
    are returned as they are (their shifts were made before the person was followed)."""
    if seen.sync.get("mode") != "report":
        return seen
    people = [{} for _ in seen.cameras]
    for i, frame in enumerate(found.frames):
        for v in np.flatnonzero(found.used[i]):
            people[v][frame] = [found.distorted[i, v]]
    estimates = estimate_offsets(seen.cameras, seen.frames, people)
    record = {name: dict(estimates[name], applied_frames=0) for name in estimates}
    return replace(seen, sync={"mode": "report", "cameras": record, "person": "the person followed"})
