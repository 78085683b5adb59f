"""The followed person in every view (docs/guides/real-captures.md, *Other people in view*): views whose detector
found somebody else, or nobody, are detected again inside a box around the person's targets projected into them,
and every kept view's mask is cut down to the parts that touch that person.

BlazePose finds the most prominent person of the image it is given; in a box around the followed person, that is
the followed person unless somebody stands in front of them.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pipelines.datasets.camera import Camera, project_distorted
from pipelines.datasets.keypoints import to_targets
from pipelines.prepare.multiview import projection_matrix, undistort_points
from pipelines.prepare.people import matches
from pipelines.prepare.person_targets import MIN_CONFIDENCE

#: the box around the projected targets grows by this fraction of its size on each side (the targets are joints:
#: the head's top, the hands and the feet lie outside them)
BOX_MARGIN = 0.3
#: boxes with fewer rows than this, or with less than half of their area inside the image, are not detected
MIN_BOX_ROWS = 32
#: a mask's parts are kept where they come within this fraction of the image height of the person's targets
CUT_RADIUS = 0.03


def crop_box(camera: Camera, points: np.ndarray) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) pixels of a square box around ``points`` (T, 3) projected into ``camera``, grown by
    ``BOX_MARGIN`` and clipped to the image; None when the person is too small or mostly outside (module
    constants)."""
    finite = points[np.isfinite(points).all(-1)]
    depth = finite @ camera.cam_from_world[2, :3] + camera.cam_from_world[2, 3]
    if len(finite) < 3 or (depth <= 0).any():
        return None
    xy = project_distorted(camera, finite)
    low, high = xy.min(0), xy.max(0)
    centre, side = (low + high) / 2, (1 + 2 * BOX_MARGIN) * (high - low).max()
    x0, y0 = np.floor(centre - side / 2).astype(int)
    x1, y1 = np.ceil(centre + side / 2).astype(int)
    clipped = max(0, x0), max(0, y0), min(camera.width, x1), min(camera.height, y1)
    inside = max(0, clipped[2] - clipped[0]) * max(0, clipped[3] - clipped[1])
    if side < MIN_BOX_ROWS or inside < 0.5 * (x1 - x0) * (y1 - y0):
        return None
    return clipped


def redetect(folder: Path, seen, route: dict, crops: dict, detector, threshold: float, progress=None) -> int:
    """Detect again, inside :func:`crop_box`, every view of a ``route`` frame (``pipelines.prepare.people.guide``)
    whose detections all miss that person; a crop that finds somebody adds that detection to the view (the
    consensus picks) and its box to ``crops[(view, frame)]`` (:func:`crop_masks` writes its mask if the person is
    kept). ``detector``: a ``pipelines.prepare.detections.CachedDetector``. Returns the number of views detected
    again."""
    count = 0
    for v, camera in enumerate(seen.cameras):
        P_v = projection_matrix(camera)
        for frame, points in route.items():
            if frame not in seen.people[v]:
                continue
            people = seen.people[v][frame]
            undistorted = [_undistorted(camera, p) for p in people]
            if any(matches(P_v, d, points, camera.height, threshold) for d in undistorted):
                continue
            box = crop_box(camera, points)
            if box is None:
                continue
            image = folder / camera.name / f"{frame:06d}.jpg"
            rgb = cv2.cvtColor(cv2.imread(str(image)), cv2.COLOR_BGR2RGB)
            keypoints, mask = detector.crop(image, rgb, box)
            count += 1
            if progress is not None:
                progress()
            if keypoints is None:
                continue
            seen.people[v][frame] = [to_targets(keypoints, "blazepose"), *people]
            crops.setdefault((v, frame), []).append(box)
    return count


def crop_masks(folder: Path, seen, found, crops: dict, detector, threshold: float) -> None:
    """For each kept view (``found``: ``pipelines.prepare.person_targets.Triangulated``) with a crop
    (:func:`redetect`) whose keypoints show the triangulated person, the crop's mask replaces the raw mask in
    ``folder/mask_raw`` (read back from the detection cache)."""
    for i, frame in enumerate(found.frames):
        for v, camera in enumerate(seen.cameras):
            for box in crops.get((v, frame), []):
                image = folder / camera.name / f"{frame:06d}.jpg"
                rgb = cv2.cvtColor(cv2.imread(str(image)), cv2.COLOR_BGR2RGB)
                keypoints, mask = detector.crop(image, rgb, box)
                detector.reused -= 1  # read back for its mask, not a view the run reused
                targets = _undistorted(camera, to_targets(keypoints, "blazepose"))
                if mask is not None and matches(
                    projection_matrix(camera), targets, found.points[i], camera.height, threshold
                ):
                    cv2.imwrite(str(folder / "mask_raw" / camera.name / f"{frame:06d}.png"), mask.astype(np.uint8))
                    break


def _undistorted(camera: Camera, targets: np.ndarray) -> np.ndarray:
    """(T, 3) targets in undistorted pixels, confidences under ``MIN_CONFIDENCE`` set to 0 (as the consensus takes
    them)."""
    confidence = np.where(targets[:, 2] >= MIN_CONFIDENCE, targets[:, 2], 0.0)
    return np.column_stack([undistort_points(camera, targets[:, :2]), confidence])


def cut_mask(mask: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """The parts (8-connected components) of ``mask`` (H, W) bool that come within ``CUT_RADIUS`` of the image
    height of the convex hull of ``pixels`` (N, 2): the followed person, without people standing apart."""
    pixels = pixels[np.isfinite(pixels).all(-1)]
    if len(pixels) < 3 or not mask.any():
        return mask
    near = np.zeros(mask.shape, np.uint8)
    hull = cv2.convexHull(np.round(pixels).astype(np.int32).clip(-(2**20), 2**20))
    cv2.fillConvexPoly(near, hull, 1)
    radius = max(1, int(round(CUT_RADIUS * mask.shape[0])))
    near = cv2.dilate(near, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1)))
    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    touching = np.unique(labels[(near > 0) & mask])
    return np.isin(labels, touching[touching > 0])


def cut_masks(folder: Path, cameras: list[Camera], found) -> None:
    """Every kept view's raw mask in ``folder/mask_raw`` cut (:func:`cut_mask`) to the triangulated person of its
    frame (``found``: ``pipelines.prepare.person_targets.Triangulated``)."""
    for i, frame in enumerate(found.frames):
        for camera in cameras:
            path = folder / "mask_raw" / camera.name / f"{frame:06d}.png"
            mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 0
            finite = found.points[i][np.isfinite(found.points[i]).all(-1)]
            depth = finite @ camera.cam_from_world[2, :3] + camera.cam_from_world[2, 3]
            if len(finite) < 3 or (depth <= 0).any():
                continue
            cut = cut_mask(mask, project_distorted(camera, finite))
            if not np.array_equal(cut, mask):
                cv2.imwrite(str(path), cut.astype(np.uint8))
