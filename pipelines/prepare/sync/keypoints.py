"""Cameras in step (docs/guides/real-captures.md, *Cameras in step*): each camera's time offset, estimated from the
keypoints, told apart from a calibration error; :mod:`pipelines.prepare.sync.apply` corrects the whole-frame part
of it by renumbering that camera's frames.

Camera c's offset d (frames) says that its frame t shows the instant of the other cameras' frame t + d: a camera
started k frames late has d = +k. For a candidate d the other cameras' keypoints of frame t + d are triangulated
(confidence-weighted DLT, ``pipelines.prepare.people.multiview``) and projected into camera c; the residual is c's own
keypoint minus that projection, as a fraction of the image height.

A time offset and a calibration error leave different marks on the residual: an error of the camera's pose or
intrinsics moves each joint's projection by about the same amount in every frame (a static part), while an offset
moves it along the joint's motion, by its image speed times d. So each joint's median residual over the frames (its
static part) is taken off before the residuals are scored (the median distance over every joint and frame): a
calibration error no longer favours any d, and the d that lowers the score is the one the motion asks for. The best
whole d is refined by the vertex of a parabola fitted to the score on a grid of tenths within 1.5 frames of it, the
others' points interpolated linearly in time.

An error of the intrinsics (focal length, principal point, distortion) moves a joint's projection by an amount that
changes with where the joint lies in the image, so as the person crosses the view it leaves a mark the static part
does not remove. The estimate is therefore made twice: with the static part alone, and with a positional part too
(the residual's best robust fit, per camera, by a 2 x 2 matrix times each joint's image position about its own median
position). The positional part can also take up motion where the person's place in the image and their speed move
together, so its estimate is kept only where it agrees with the static part's within ``POSITION_AGREEMENT`` frames for
every camera; otherwise the static part's is.

A camera out of step spoils the triangulation that every other camera is judged by, so whole-frame shifts are chosen
for the capture as a whole: among each camera's best whole shifts (and their neighbours), the one that lowers the
capture's error (the mean over cameras of the score in step) most is made, if it lowers it by ``MIN_TOTAL_GAIN`` at
least, and the search repeats; what is left below a frame is reported. Beside it, Pose2Sim's calibration-free
estimate (the lag that best correlates a camera's keypoint speeds with the others') is a second opinion, and with one
person in view the silhouettes give another that does not go through the keypoints
(:mod:`pipelines.prepare.sync.silhouettes`). The speed correlation shifts nothing; the silhouettes' look is averaged
with this one where the two agree (:mod:`pipelines.prepare.sync.apply`).

Each view's person is its most confident detection (summed confidence): one person in view, or the one nearest the
cameras, dominates.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np

from pipelines.datasets.keypoints import TARGETS, mirror_index
from pipelines.prepare.people.multiview import project, projection_matrix, triangulate_robust, undistort_points

#: frames searched each way
MAX_OFFSET = 10
#: fewest (frame, joint) pairs an offset must be scored on
MIN_PAIRS = 30
#: keypoints below this confidence take no part
MIN_CONFIDENCE = 0.3
#: a view whose keypoint reprojects further than this (fraction of the height) leaves that joint's triangulation
TRIANGULATION_ERROR = 0.03
#: the least share of the capture's error that a whole-frame shift must take off to be made. On the unmodified
#: Pose2Sim demo the best shift of any camera takes off 0.6 %, a camera cut 3 frames late 24 % and one cut by 1
#: frame (17 ms at 60 fps) about 4 %: one frame is what that recording cannot tell from its calibration
MIN_TOTAL_GAIN = 0.05
#: a shift that takes off this share or more is "high" confidence
HIGH_TOTAL_GAIN = 0.10
#: the least share of a camera's own error that its remaining (sub-frame) offset must take off to be reported as an
#: offset rather than "in step"
MIN_GAIN = 0.1
#: the correlation of keypoint speeds below which the second opinion has nothing to say
MIN_CORRELATION = 0.3
#: each target's left/right counterpart
MIRRORED = [mirror_index(t) for t in range(len(TARGETS))]
METHOD = "reprojection of the others' triangulation, each joint's static part removed"
METHOD_POSITIONAL = METHOD + ", and a part that grows with the joint's place in the image"
#: the most (frames) the estimate with the positional part may differ from the static part's, for any camera, to be
#: kept: on Pose2Sim's two takes it agrees within 0.9 frame wherever it is right and departs by 2.5-4 frames where the
#: man's place and speed move together in cam03 (docs/results/real-capture.md, *Cameras in step*)
POSITION_AGREEMENT = 1.0
#: rounds of reweighting in the positional part's robust fit
POSITION_ROUNDS = 5
#: tenths of a frame either side of the best whole offset through which the score's parabola is fitted (1.5 frames)
PARABOLA_STEPS = 15


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


def shifted_keypoints(keypoints: np.ndarray, v: int, shift: int) -> np.ndarray:
    """(V, N, T, 3) keypoints with camera v's frames renumbered from n to n + ``shift`` (as :func:`shift_camera` does
    to its files); what leaves the timeline is dropped, what enters it is unseen."""
    out = keypoints.copy()
    out[v] = 0
    n = keypoints.shape[1]
    if abs(shift) < n:
        if shift >= 0:
            out[v, shift:] = keypoints[v, : n - shift]
        else:
            out[v, : n + shift] = keypoints[v, -shift:]
    return out


@dataclass
class _Rig:
    """The cameras' projections P (V, 3, 4) and heights (V,), and the keypoints (V, N, T, 3) being judged."""

    P: np.ndarray
    heights: np.ndarray
    keypoints: np.ndarray
    #: whether the residual's positional part is taken off too (module docstring)
    positional: bool = False

    def others_points(self, v: int) -> np.ndarray:
        """(N, T, 3) the triangulation of every camera but v (NaN where fewer than two see a joint)."""
        others = [o for o in range(len(self.P)) if o != v]
        xy = self.keypoints[others].transpose(1, 2, 0, 3)
        return triangulate_robust(self.P[others], xy[..., :2], xy[..., 2], self.heights[others], TRIANGULATION_ERROR)[0]

    def error(self, v: int, points: np.ndarray, d: float) -> tuple[float, int]:
        """Camera v's score against ``points`` at offset d: the median over joints and frames of the residual's
        length with each joint's static part (its median over the frames) removed, and the pairs scored (inf below
        ``MIN_PAIRS``). Each frame's detection is taken as it is or with left and right swapped, whichever lies
        nearer: detectors swap the sides of a person seen from the back."""
        residual = _residuals(self.P[v], self.heights[v], _shifted(points, d), self.keypoints[v])
        with warnings.catch_warnings():  # a joint never seen gives an all-NaN median
            warnings.simplefilter("ignore", RuntimeWarning)
            residual = residual - np.nanmedian(residual, axis=0, keepdims=True)
        if self.positional:
            residual = residual - positional_part(residual, self.keypoints[v][..., :2] / self.heights[v])
        length = np.linalg.norm(residual, axis=-1)
        usable = np.isfinite(length)
        return (float(np.median(length[usable])) if usable.sum() >= MIN_PAIRS else np.inf), int(usable.sum())

    def capture_error(self) -> float:
        """The mean over cameras of each one's score in step (a camera that cannot be scored counts as inf)."""
        return float(np.mean([self.error(v, self.others_points(v), 0.0)[0] for v in range(len(self.P))]))

    def estimate(self, v: int, max_offset: int) -> dict:
        """Camera v's best offset (whole frames, then tenths) with its scores; {} when it cannot be scored."""
        points = self.others_points(v)
        scores = {d: self.error(v, points, d) for d in range(-max_offset, max_offset + 1)}
        # an offset is judged on at least half the pairs that being in step is: a shift that leaves a few frames
        # overlapping would be scored on them alone
        enough = scores[0][1] / 2
        scores = {d: (e, n) if n >= enough else (np.inf, n) for d, (e, n) in scores.items()}
        best = min(scores, key=lambda d: scores[d][0])
        if not np.isfinite(scores[best][0]):
            return {}
        grid = best + np.arange(-PARABOLA_STEPS, PARABOLA_STEPS + 1) / 10
        fine = np.array([self.error(v, points, d)[0] for d in grid])
        offset, at = parabola_vertex(grid, fine)
        return {"offset": round(offset, 2), "in_step": scores[0][0], "at_offset": at, "pairs": scores[best][1]}


def parabola_vertex(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(x*, y*) the vertex of the least-squares parabola y ~ a x^2 + b x + c through the finite points (x (K,), y
    (K,)), x* = -b / 2a kept within [x.min(), x.max()]; the lowest point where the fit does not open upwards. A median
    score is flat within its noise near its minimum (1-2 % from one tenth of a frame to the next on the Pose2Sim demo,
    docs/results/real-capture.md, *Cameras in step*), so its lowest point wanders over that flat; the parabola
    through the whole reach does not."""
    known = np.isfinite(y)
    x, y = x[known], y[known]
    lowest = int(np.argmin(y))
    if len(x) < 3:
        return float(x[lowest]), float(y[lowest])
    centre = x.mean()
    a, b, c = np.polyfit(x - centre, y, 2)
    if a <= 0:
        return float(x[lowest]), float(y[lowest])
    vertex = float(np.clip(-b / (2 * a), x.min() - centre, x.max() - centre))
    return vertex + centre, float(a * vertex**2 + b * vertex + c)


def _residuals(P: np.ndarray, height: float, points: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
    """(N, T, 2) keypoints minus the projection of ``points`` (N, T, 3), over ``height``; NaN where either is
    missing; per frame with the sides swapped where that lies nearer."""
    projected = project(P[None], points)[..., 0, :]

    def of(kp: np.ndarray) -> np.ndarray:
        residual = (kp[..., :2] - projected) / height
        return np.where(((kp[..., 2] > 0) & np.isfinite(residual).all(-1))[..., None], residual, np.nan)

    plain, swapped = of(keypoints), of(keypoints[:, MIRRORED])
    with warnings.catch_warnings():  # frames with no scored joint give an all-NaN median
        warnings.simplefilter("ignore", RuntimeWarning)
        nearer = np.nanmedian(np.linalg.norm(swapped, axis=-1), 1) < np.nanmedian(np.linalg.norm(plain, axis=-1), 1)
    return np.where(nearer[:, None, None], swapped, plain)


def positional_part(residual: np.ndarray, position: np.ndarray) -> np.ndarray:
    """(N, T, 2) the part of a camera's residuals (N, T, 2; each joint's static part already taken off; NaN where
    missing) that a 2 x 2 matrix A explains from each joint's image position (N, T, 2, over the height) about that
    joint's median position over the frames: r ~ A (x - median_n x), fitted by least squares reweighted
    ``POSITION_ROUNDS`` times (weights sqrt(min(1, s / |e|)), s 1.5 x the median |e|: a Huber-like fit that outliers do
    not pull). Zero where fewer than ``MIN_PAIRS`` pairs are known."""
    known = np.isfinite(residual).all(-1) & np.isfinite(position).all(-1)
    out = np.zeros_like(residual)
    if known.sum() < MIN_PAIRS:
        return out
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        centred = position - np.nanmedian(np.where(known[..., None], position, np.nan), axis=0, keepdims=True)
    x, y = centred[known], residual[known]
    weights = np.ones(len(x))
    for _ in range(POSITION_ROUNDS):
        A = np.linalg.lstsq(x * weights[:, None], y * weights[:, None], rcond=None)[0]
        error = np.linalg.norm(y - x @ A, axis=-1)
        scale = 1.5 * np.median(error) + 1e-12
        weights = np.sqrt(np.minimum(1.0, scale / np.maximum(error, 1e-12)))
    out[known] = x @ A
    return out


def speed_lags(keypoints: np.ndarray, heights: np.ndarray, max_offset: int = MAX_OFFSET) -> list[tuple]:
    """Pose2Sim's calibration-free estimate of every camera's offset, from keypoint speeds alone: each camera's
    speed curve s_v(t) (the median over joints of each joint's image step between frames, over the height, smoothed
    over 5 frames, standardised); for each pair the lag L_vw that best correlates s_v(t) with s_w(t + L), below a
    frame by a parabola through the peak; then the offsets d that best explain d_v - d_w = L_vw (least squares), the
    median camera's set to 0. Returns per camera (d, the mean peak correlation of its pairs); (None, 0) for every
    camera when one has too few steps to compare."""
    steps = np.linalg.norm(np.diff(keypoints[..., :2], axis=1), axis=-1) / heights[:, None, None]
    seen = (keypoints[:, 1:, :, 2] > 0) & (keypoints[:, :-1, :, 2] > 0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        speeds = np.nanmedian(np.where(seen, steps, np.nan), axis=2)  # (V, N-1)
    curves = []
    for curve in speeds:
        known = np.flatnonzero(np.isfinite(curve))
        if len(known) < 2 * max_offset + 3:
            return [(None, 0.0)] * len(speeds)
        curve = np.convolve(np.interp(np.arange(len(curve)), known, curve[known]), np.ones(5) / 5, mode="same")
        curves.append((curve - curve.mean()) / max(curve.std(), 1e-12))
    n_cameras = len(curves)
    rows, lags, peaks = [], [], np.zeros((n_cameras, n_cameras))
    for v in range(n_cameras):
        for w in range(v + 1, n_cameras):
            lag, peaks[v, w] = _correlation_peak(curves[v], curves[w], max_offset)
            row = np.zeros(n_cameras)
            row[v], row[w] = 1.0, -1.0
            rows.append(row)
            lags.append(lag)
    offsets = np.linalg.lstsq(np.array(rows), np.array(lags), rcond=None)[0]
    offsets -= np.median(offsets)
    peaks = peaks + peaks.T
    return [(round(float(d), 1), round(float(peaks[v].sum() / (n_cameras - 1)), 3)) for v, d in enumerate(offsets)]


def _correlation_peak(own: np.ndarray, other: np.ndarray, max_offset: int) -> tuple[float, float]:
    """The lag L in [-max_offset, max_offset] that maximises the mean of own(t) other(t + L), below a frame by a
    parabola through the peak, and the peak."""
    n = len(own)
    scores = {
        lag: float(np.mean(own[max(0, -lag) : n - max(0, lag)] * other[max(0, lag) : n + min(0, lag)]))
        for lag in range(-max_offset, max_offset + 1)
    }
    best = max(scores, key=scores.get)
    fraction = 0.0
    if -max_offset < best < max_offset:
        before, peak, after = scores[best - 1], scores[best], scores[best + 1]
        curvature = before - 2 * peak + after
        fraction = 0.5 * (before - after) / curvature if curvature < 0 else 0.0
    return best + fraction, scores[best]


def find_offsets(cameras, frames, people, max_offset: int = MAX_OFFSET) -> dict[str, dict]:
    """Every camera's time offset and how sure it is (module docstring), in frames of the timeline read.

    Returns, per camera: ``whole_frames`` (the whole-frame shift the capture asks for), ``offset_frames`` (that plus
    what is left below a frame), ``status`` (``in step``, ``out of step``, or ``uncertain``: its own error asks for an
    offset that the capture's does not confirm), ``confidence`` (``high`` or ``low``), ``evidence`` (the share of the
    capture's error its shift takes off, or of its own error its remaining offset would), ``method`` (which of the two
    estimates was kept), ``error_in_step_pct`` / ``error_at_offset_pct`` (its score, % of the height, after the shifts)
    and ``pairs``, and Pose2Sim's ``speed_correlation`` (lag, peak) with whether it agrees; a camera that cannot be
    scored (fewer than three cameras, too few joints seen) gets a ``note``."""
    _, keypoints = _keypoints(cameras, frames, people)
    rig = _Rig(
        np.stack([projection_matrix(c) for c in cameras]), np.array([c.height for c in cameras], float), keypoints
    )
    names = [c.name for c in cameras]
    if len(cameras) < 3:
        return {
            n: {"offset_frames": 0.0, "whole_frames": 0, "note": "fewer than three cameras: not estimated"}
            for n in names
        }
    static = _search(rig, names, max_offset)
    positional = _search(replace(rig, positional=True), names, max_offset)
    chosen, method = static, METHOD
    if _agree(static, positional, names):
        chosen, method = positional, METHOD_POSITIONAL
    estimates, whole, drops = chosen
    speed = speed_lags(keypoints, rig.heights, max_offset)
    return {n: _entry(estimates[v], speed[v], whole[n], drops.get(n), method) for v, n in enumerate(names)}


def _search(rig: _Rig, names: list[str], max_offset: int) -> tuple[list[dict], dict[str, int], dict[str, float]]:
    """The whole-frame shifts made one at a time while the best lowers the capture's error by ``MIN_TOTAL_GAIN`` (the
    module docstring): (each camera's estimate after them, the shifts by camera name, the share of the capture's
    error each shifted camera's shifts took off)."""
    whole, drops = {n: 0 for n in names}, {}
    current = rig.capture_error()
    estimates = [rig.estimate(v, max_offset) for v in range(len(names))]  # always those of the current shifts
    for _ in range(len(names)):
        best = _best_shift(rig, estimates, max_offset, whole)
        if best is None or not np.isfinite(current) or best[0] > current * (1 - MIN_TOTAL_GAIN):
            break
        error, v, shift = best
        rig = replace(rig, keypoints=shifted_keypoints(rig.keypoints, v, shift))
        whole[names[v]] += shift
        drops[names[v]] = drops.get(names[v], 0.0) + 1 - error / current
        current = error
        estimates = [rig.estimate(u, max_offset) for u in range(len(names))]
    return estimates, whole, drops


def _agree(static: tuple, positional: tuple, names: list[str]) -> bool:
    """Whether every camera's offset (whole shift plus what is left) from the two searches (:func:`_search`) lies
    within ``POSITION_AGREEMENT`` frames; a camera that either search cannot score counts as disagreeing."""
    for v, name in enumerate(names):
        ends = []
        for estimates, whole, _ in (static, positional):
            if not estimates[v]:
                return False
            ends.append(whole[name] + estimates[v]["offset"])
        if abs(ends[0] - ends[1]) > POSITION_AGREEMENT:
            return False
    return True


def _best_shift(rig: _Rig, estimates: list[dict], max_offset: int, whole: dict[str, int]):
    """(capture error after, camera, shift) of the whole-frame shift that lowers the capture's error most, among
    each camera's best whole offset (``estimates``, :meth:`_Rig.estimate`) and its two neighbours, none taking a
    camera further than ``max_offset`` in all (``whole``: the shifts so far, by camera in order); None when no
    camera has one."""
    candidates = []
    for v, (estimate, so_far) in enumerate(zip(estimates, whole.values())):
        if not estimate:
            continue
        shifts = {int(round(estimate["offset"])) + k for k in (-1, 0, 1)} - {0}
        for shift in (s for s in shifts if abs(so_far + s) <= max_offset):
            candidates.append(
                (replace(rig, keypoints=shifted_keypoints(rig.keypoints, v, shift)).capture_error(), v, shift)
            )
    return min(candidates) if candidates else None


def _entry(estimate: dict, speed: tuple, whole: int, drop: float | None, method: str = METHOD) -> dict:
    """A camera's record (:func:`find_offsets`) from its estimate after the shifts (:meth:`_Rig.estimate`), its
    speed-correlation lag and peak, its whole shift, the share of the capture's error that shift took off and the
    method that made the estimate."""
    if not estimate:
        return {
            "offset_frames": float(whole),
            "whole_frames": whole,
            "note": "too few joints seen by it and two others",
        }
    rest = estimate["offset"]
    own = 1 - estimate["at_offset"] / estimate["in_step"] if estimate["in_step"] > 0 else 0.0
    if whole:
        status, evidence = "out of step", drop
        confidence = "high" if drop >= HIGH_TOTAL_GAIN else "low"
    elif abs(rest) >= 0.5 and own >= MIN_GAIN:  # its own error asks for an offset the capture's does not confirm
        status, evidence, confidence = "uncertain", own, "low"
    else:
        status, evidence = "in step", own
        confidence = "high" if abs(rest) < 0.5 and own < MIN_GAIN else "low"
    lag, peak = speed
    offset = whole + rest
    agrees = None if lag is None or peak < MIN_CORRELATION else bool(abs(lag - offset) <= 1.0)
    return {
        "offset_frames": float(offset),
        "whole_frames": whole,
        "status": status,
        "confidence": confidence,
        "evidence": round(float(evidence), 3),
        "method": method,
        "error_in_step_pct": 100 * estimate["in_step"],
        "error_at_offset_pct": 100 * estimate["at_offset"],
        "pairs": estimate["pairs"],
        "speed_correlation": {"offset_frames": lag, "peak": peak, "agrees": agrees},
    }


def triangulated_joints(cameras, frames, people) -> tuple[list[int], np.ndarray]:
    """(the frames any camera read, (N, T, 3) each view's most confident person's joints triangulated from every
    camera, a view more than ``TRIANGULATION_ERROR`` off left out; NaN where under two views see a joint)."""
    timeline, keypoints = _keypoints(cameras, frames, people)
    P = np.stack([projection_matrix(c) for c in cameras])
    heights = np.array([c.height for c in cameras], float)
    xy = keypoints.transpose(1, 2, 0, 3)
    return timeline, triangulate_robust(P, xy[..., :2], xy[..., 2], heights, TRIANGULATION_ERROR)[0]
