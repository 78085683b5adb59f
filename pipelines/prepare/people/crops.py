"""The followed person in every view (docs/guides/real-captures.md, *Other people in view*): views whose detector
found somebody else, or nobody, are detected again inside a box around the person's targets projected into them,
and every kept view's mask is cut down to the parts that touch that person.

BlazePose finds the most prominent person of the image it is given; in a box around the followed person, that is
the followed person unless somebody stands in front of them.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

from fitting.files import write_image
from pipelines.datasets.camera import Camera, project_distorted
from pipelines.datasets.keypoints import mirror_index, to_targets
from pipelines.prepare.people.multiview import projection_matrix, undistort_points
from pipelines.prepare.people.targets import MIN_CONFIDENCE
from pipelines.prepare.people.tracks import matches

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
    xy = _pixels(camera, points)
    if len(xy) < 3:
        return None
    low, high = xy.min(0), xy.max(0)
    centre, side = (low + high) / 2, (1 + 2 * BOX_MARGIN) * (high - low).max()
    x0, y0 = np.floor(centre - side / 2).astype(int)
    x1, y1 = np.ceil(centre + side / 2).astype(int)
    clipped = max(0, x0), max(0, y0), min(camera.width, x1), min(camera.height, y1)
    inside = max(0, clipped[2] - clipped[0]) * max(0, clipped[3] - clipped[1])
    if side < MIN_BOX_ROWS or inside < 0.5 * (x1 - x0) * (y1 - y0):
        return None
    return clipped


def redetect(folder: Path, seen, route: dict, crops: dict, detector, threshold: float, others=None, progress=None):
    """Detect again, inside :func:`crop_box`, every view of a ``route`` frame
    (``pipelines.prepare.people.tracks.guide``) whose detections all miss that person, with the other people of the
    frame (``others[frame]``: (T, 3) targets) painted grey where they do not overlap the person (:func:`painted_crop`).
    A crop that finds somebody adds that detection to the view (the consensus picks) and (box, cache key) to
    ``crops[(view, frame)]`` (:func:`crop_masks` writes its mask if the person is kept). ``detector``: a
    ``pipelines.prepare.sources.detections.CachedDetector``; ``progress()`` is called once per view looked at. Returns
    the number of views detected again."""
    count = 0
    for v, camera in enumerate(seen.cameras):
        for frame, points in route.items():
            if progress is not None:
                progress()
            if frame not in seen.people[v]:
                continue
            people = seen.people[v][frame]
            if any(_shows(camera, p, points, threshold) for p in people):
                continue
            box = crop_box(camera, points)
            if box is None:
                continue
            rgb = cv2.cvtColor(cv2.imread(str(folder / camera.name / f"{frame:06d}.jpg")), cv2.COLOR_BGR2RGB)
            crop = painted_crop(rgb, box, camera, points, (others or {}).get(frame, []))
            keypoints, _, key = detector.crop(crop, box)
            count += 1
            if keypoints is not None:
                seen.people[v][frame] = [to_targets(keypoints, "blazepose"), *people]
                crops.setdefault((v, frame), []).append((box, key))
    return count


def redetect_masks(
    folder: Path, seen, found, crops: dict, detector, threshold: float, others=None, progress=None
) -> int:
    """With keypoints from files and masks from the segmenter: each view of ``found``'s frames
    (``pipelines.prepare.people.targets.Triangulated``) whose mask came with a detection of somebody else, or that
    has no mask since the detector found nobody (``seen.mask_owners``), is detected again around the person
    (:func:`redetect`), so that :func:`crop_masks` gives it the crop's mask or leaves it out; a mask that came with
    no detection (a segmenter alone) is kept. The files' people are left as they are. ``progress()`` is called once
    per view looked at. Returns the number of views detected again."""
    people = [{f: [owner] for f, owner in by_frame.items()} for by_frame in seen.mask_owners]
    route = {frame: found.points[i] for i, frame in enumerate(found.frames)}
    seen_masks = SimpleNamespace(cameras=seen.cameras, people=people)
    return redetect(folder, seen_masks, route, crops, detector, threshold, others, progress)


def painted_crop(rgb: np.ndarray, box, camera: Camera, points: np.ndarray, others: list[np.ndarray]) -> np.ndarray:
    """``rgb[box]`` with each of ``others`` (people's (T, 3) targets) painted mid-grey over the hull of its
    projected targets grown by ``CUT_RADIUS`` of the height, except where that comes near the followed person's
    (``points``): the detector, which finds the most prominent person, is left with the followed one."""
    x0, y0, x1, y1 = box
    crop = rgb[y0:y1, x0:x1].copy()
    if not others:
        return crop
    offset = np.array([x0, y0])
    keep = _near(crop.shape[:2], _pixels(camera, points) - offset, 2 * CUT_RADIUS * camera.height)
    for other in others:
        pixels = _pixels(camera, other)
        if len(pixels) >= 3:
            crop[_near(crop.shape[:2], pixels - offset, CUT_RADIUS * camera.height) & ~keep] = 127
    return crop


def _pixels(camera: Camera, points: np.ndarray) -> np.ndarray:
    """(N, 2) distorted pixels of the finite ``points`` in front of ``camera`` (empty when any is behind)."""
    finite = points[np.isfinite(points).all(-1)]
    depth = finite @ camera.cam_from_world[2, :3] + camera.cam_from_world[2, 3]
    if len(finite) == 0 or (depth <= 0).any():
        return np.zeros((0, 2))
    return project_distorted(camera, finite)


def _near(shape: tuple[int, int], pixels: np.ndarray, radius: float) -> np.ndarray:
    """(H, W) bool: the convex hull of ``pixels`` grown by ``radius`` pixels (all False under three pixels)."""
    near = np.zeros(shape, np.uint8)
    if len(pixels) < 3:
        return near > 0
    hull = cv2.convexHull(np.round(pixels).clip(-(2**20), 2**20).astype(np.int32))
    cv2.fillConvexPoly(near, hull, 1)
    r = max(1, int(round(radius)))
    return cv2.dilate(near, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) > 0


def crop_masks(folder: Path, seen, found, crops: dict, whole: dict, detector, threshold: float) -> int:
    """Each used view of ``found`` (``pipelines.prepare.people.targets.Triangulated``) takes the mask that came with
    a detection of the person: a crop's (:func:`redetect`; read back from the detection cache) replaces the raw mask
    in ``folder/mask_raw``; the whole image's detection (``whole[(view, frame)]``, targets) keeps it. A view where
    neither shows the person has only somebody else's mask: it is no longer used (``found.used``). Returns the
    number of such views."""
    dropped = 0
    for i, frame in enumerate(found.frames):
        for v, camera in enumerate(seen.cameras):
            if not found.used[i, v]:
                continue
            for (x0, y0, x1, y1), key in crops.get((v, frame), []):
                keypoints, mask = detector.kept_crop(key, (y1 - y0, x1 - x0))
                targets = to_targets(keypoints + np.array([x0, y0, 0.0]), "blazepose")
                if mask is not None and _shows(camera, targets, found.points[i], threshold):
                    pasted = np.zeros((camera.height, camera.width), np.uint8)
                    pasted[y0:y1, x0:x1] = mask
                    write_image(folder / "mask_raw" / camera.name / f"{frame:06d}.png", pasted)
                    break
            else:
                if (v, frame) in whole and not _shows(camera, whole[(v, frame)], found.points[i], threshold):
                    found.used[i, v] = False
                    dropped += 1
    return dropped


def _shows(camera: Camera, targets: np.ndarray, points: np.ndarray, threshold: float) -> bool:
    """Whether a view's ``targets`` (T, 3, distorted pixels) show the person ``points`` (``people.matches``), as
    detected or with left and right swapped (detectors swap the sides of a person seen from the back, and the
    consensus takes either)."""
    P_v, undistorted = projection_matrix(camera), _undistorted(camera, targets)
    mirrored = undistorted[[mirror_index(t) for t in range(len(undistorted))]]
    return any(matches(P_v, d, points, camera.height, threshold) for d in (undistorted, mirrored))


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
    _, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    touching = np.unique(labels[_near(mask.shape, pixels, CUT_RADIUS * mask.shape[0]) & mask])
    return np.isin(labels, touching[touching > 0])


def cut_masks(folder: Path, cameras: list[Camera], found) -> None:
    """Every kept view's raw mask in ``folder/mask_raw`` cut (:func:`cut_mask`) to the triangulated person of its
    frame (``found``: ``pipelines.prepare.people.targets.Triangulated``)."""
    for i, frame in enumerate(found.frames):
        for camera in cameras:
            path = folder / "mask_raw" / camera.name / f"{frame:06d}.png"
            mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 0
            pixels = _pixels(camera, found.points[i])
            cut = cut_mask(mask, pixels) if len(pixels) >= 3 else mask
            if not np.array_equal(cut, mask):
                write_image(path, cut.astype(np.uint8))
