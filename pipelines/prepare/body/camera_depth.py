"""Each camera's distance to the person, checked on the masks at full size (docs/guides/real-captures.md, step 6).

The body fit's silhouette stage corrects every camera's turn and shift, but on masks reduced to a few hundred rows
(``pipelines.body.silhouettes``): there a camera that stands a few centimetres nearer or further than calibrated
draws the body a pixel larger or smaller at the masks' own size, less than a reduced pixel, and nothing moves it.
Moving a camera by ``d`` along its axis scales the image of a body at depth ``Z`` by about ``Z / (Z - d)``, which no
turn and no shift across the axis does. So after the body fit each camera is tried at distances within
``DEPTH_RANGE`` of its distance to the body (steps of ``DEPTH_STEP``) on up to ``DEPTH_VIEWS`` of its views: the
fitted body drawn at full size against the person's mask (:func:`disagreement`), the step with the least
disagreement refined by the parabola through it and its neighbours (:func:`search_depth`).

What every camera finds alike is not a camera's: a body drawn a little larger than the masks in every view (a
segmenter that draws people thin, a rasteriser that covers each triangle's edge pixels) looks like every camera
standing a little too near. So the median of the cameras' best places is taken off each (:func:`settle`), and a
camera is moved by what is left only where that lowers its disagreement by at least ``DEPTH_MIN_GAIN`` of itself.
A camera in whose images the person stands under ``DEPTH_MIN_HEIGHT`` pixels tall is not searched: a step then
changes the body's outline by less than a pixel. The common part needs ``DEPTH_MIN_SEARCHED`` searched cameras: with
one, all it finds is common; with two, the median is their mean and the camera that is off would get half its move.
With fewer, no camera is moved and each searched one says so; the report counts the cameras searched.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipelines.datasets.camera import Camera, silhouette
from pipelines.prepare.body.masks import staged_person_mask

#: the distances tried: within this fraction of the camera's distance to the body, either way ...
DEPTH_RANGE = 0.03
#: ... in steps of this fraction
DEPTH_STEP = 0.005
#: at most this many views a camera (spread over the take) enter the search
DEPTH_VIEWS = 20
#: a move is applied where it lowers the disagreement by at least this fraction of the disagreement in place
DEPTH_MIN_GAIN = 0.02
#: the person's median height in a camera's masks (pixels) below which the camera is not searched: a step (0.5 %)
#: then moves the outline by under a pixel on each side
DEPTH_MIN_HEIGHT = 400
#: cameras searched below which the common part cannot be told from one camera's own (module docstring)
DEPTH_MIN_SEARCHED = 3


@dataclass(frozen=True)
class DepthCheck:
    """One camera's check: ``metres`` the move along its axis applied (positive: nearer the person; 0 when not
    applied), ``fraction`` the move found as a fraction of ``distance`` (the median depth of the body's vertices,
    metres; the common part taken off), and ``before`` / ``after`` the disagreement (:func:`disagreement`) in place
    and at the move applied."""

    metres: float
    fraction: float
    distance: float
    before: float
    after: float

    def record(self) -> dict:
        """The entries of ``report.json``'s ``calibration_correction`` (docs/guides/real-captures.md, step 6)."""
        return {
            "depth_cm": 100 * self.metres,
            "depth_found_pct": 100 * self.fraction,
            "distance_m": self.distance,
            "silhouette_disagreement_before": self.before,
            "silhouette_disagreement_after": self.after,
        }


def moved_along_axis(camera: Camera, metres: float) -> Camera:
    """``camera`` moved ``metres`` along its optical axis (towards what it looks at for metres > 0): every point's
    depth in the camera's frame falls by ``metres``, ``t_z' = t_z - metres``; the turn and the intrinsics stay."""
    pose = np.array(camera.cam_from_world, dtype=np.float64, copy=True)
    pose[2, 3] -= metres
    return replace(camera, cam_from_world=pose)


#: a view of the check: the body's vertices (N, 3) in the world, the person's mask and the pixels of unknown owner
View = tuple[np.ndarray, np.ndarray, np.ndarray]


def disagreement(camera: Camera, views: list[View], faces: np.ndarray) -> float:
    """Pixels where the body and the person's mask disagree, over the mask's pixels, summed over ``views``: each a
    (vertices (N, 3), mask (H, W) bool, unknown (H, W) bool) triple, the body drawn by :func:`silhouette` less the
    pixels of unknown owner (``mask_unknown/``, which the mask leaves out)."""
    wrong = sum(int(((silhouette(camera, v, faces) & ~unknown) ^ mask).sum()) for v, mask, unknown in views)
    return wrong / max(sum(int(mask.sum()) for _, mask, _ in views), 1)


@dataclass(frozen=True)
class DepthSearch:
    """One camera's scores: ``distance`` (the median depth of the body's vertices, metres), the disagreement
    ``scores`` at ``steps`` (fractions of the distance, 0 in the middle) and ``best`` the fraction where it is least
    (the parabola's vertex)."""

    distance: float
    steps: np.ndarray
    scores: np.ndarray
    best: float


def search_depth(camera: Camera, views: list[View], faces: np.ndarray) -> DepthSearch:
    """The search of the module docstring for one camera over ``views`` (as :func:`disagreement`'s)."""
    row = camera.cam_from_world[2]
    distance = float(np.median(np.concatenate([np.asarray(v, np.float64) @ row[:3] + row[3] for v, _, _ in views])))
    steps = np.arange(-round(DEPTH_RANGE / DEPTH_STEP), round(DEPTH_RANGE / DEPTH_STEP) + 1) * DEPTH_STEP
    scores = np.array([disagreement(moved_along_axis(camera, s * distance), views, faces) for s in steps])
    k = int(np.argmin(scores))
    best = float(steps[k])
    if 0 < k < len(steps) - 1:  # the vertex of the parabola through the best step and its neighbours
        left, mid, right = scores[k - 1 : k + 2]
        curvature = left - 2 * mid + right
        if curvature > 0:
            best += float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5)) * DEPTH_STEP
    return DepthSearch(distance, steps, scores, best)


def common_fraction(searches: list[DepthSearch]) -> float:
    """What the cameras find alike: the median of their best places (0 without any)."""
    return float(np.median([s.best for s in searches])) if searches else 0.0


def settle(camera: Camera, search: DepthSearch, views: list[View], faces: np.ndarray, common: float) -> DepthCheck:
    """The camera's move: its best place less ``common`` (:func:`common_fraction`), applied where it lowers the
    disagreement over ``views`` by at least ``DEPTH_MIN_GAIN`` of the disagreement in place."""
    fraction = search.best - common
    before = float(search.scores[len(search.steps) // 2])
    after = disagreement(moved_along_axis(camera, fraction * search.distance), views, faces)
    if after >= before * (1 - DEPTH_MIN_GAIN):  # in place, or a gain within the scores' own noise
        return DepthCheck(0.0, fraction, search.distance, before, before)
    return DepthCheck(fraction * search.distance, fraction, search.distance, before, after)


def person_height(views: list[View]) -> float:
    """The median over ``views`` of the rows the person's mask spans (pixels; 0 without any)."""
    spans = [np.ptp(np.flatnonzero(mask.any(1))) + 1 for _, mask, _ in views if mask.any()]
    return float(np.median(spans)) if spans else 0.0


def spread_views(used: np.ndarray, count: int = DEPTH_VIEWS) -> list[int]:
    """Up to ``count`` frame indices of the True entries of ``used`` (F,), evenly spread over them."""
    frames = np.flatnonzero(used)
    if len(frames) <= count:
        return frames.tolist()
    return frames[np.linspace(0, len(frames) - 1, count).round().astype(int)].tolist()


def check_camera_depths(root: Path, seen, found, vertices: np.ndarray, faces: np.ndarray):
    """``seen`` with every camera checked and moved as the module docstring says, on its used views of ``found`` (the
    raw masks in ``root/.frames/mask_raw``, reduced to the person's as the capture's own masks are,
    ``pipelines.prepare.body.masks.staged_person_mask``) against the fitted ``vertices`` (F, N, 3); the checks' records
    in ``seen.depths`` (a camera not searched: ``{"depth_cm": 0.0, "depth_skipped": why}``)."""

    def views_of(v: int, camera: Camera) -> list[View]:
        views = []
        for i in spread_views(found.used[:, v]):
            mask, unknown = staged_person_mask(root, camera, found, i, silhouette(camera, vertices[i], faces))
            views.append((vertices[i], mask, unknown))
        return views

    searches, records = {}, {}
    for v, camera in enumerate(seen.cameras):
        views = views_of(v, camera)
        height = person_height(views)
        if height < DEPTH_MIN_HEIGHT:
            records[camera.name] = {"depth_cm": 0.0, "depth_skipped": f"the person is {height:.0f} px tall"}
            continue
        searches[v] = search_depth(camera, views, faces)
    cameras, placed = place_cameras(list(seen.cameras), searches, views_of, faces)
    return replace(seen, cameras=cameras, depths={**records, **placed})


def place_cameras(cameras: list[Camera], searches: dict, views_of, faces: np.ndarray) -> tuple[list[Camera], dict]:
    """The cameras moved by their searches (``searches``: camera index -> :class:`DepthSearch`; ``views_of(v,
    camera)`` reads a camera's views again, so that no camera's masks are held while others are read), and each
    searched camera's record, ``depth_searched`` the number of cameras searched. Under ``DEPTH_MIN_SEARCHED`` none is
    moved (module docstring)."""
    cameras, records, count = list(cameras), {}, len(searches)
    if count < DEPTH_MIN_SEARCHED:
        why = f"{count} camera{'s' * (count != 1)} searched: the common part needs {DEPTH_MIN_SEARCHED}"
        for v, search in searches.items():
            records[cameras[v].name] = {
                "depth_cm": 0.0,
                "depth_found_pct": 100 * search.best,
                "depth_skipped": why,
                "depth_searched": count,
            }
        return cameras, records
    common = common_fraction(list(searches.values()))
    for v, search in searches.items():
        check = settle(cameras[v], search, views_of(v, cameras[v]), faces, common)
        records[cameras[v].name] = {**check.record(), "depth_common_pct": 100 * common, "depth_searched": count}
        cameras[v] = moved_along_axis(cameras[v], check.metres)
    return cameras, records
