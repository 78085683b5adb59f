"""People who overlap the followed person in a view (docs/guides/real-captures.md, *Other people in view*).

The segmenter gives one mask a view, of the person the detector found, with whatever of the others touches them, and
where two people overlap in the image the detector finds whichever is more prominent, in a crop too; the mask then
lacks that person's limbs over the other (docs/results/real-capture.md, *Measured, not kept*). Both people are
triangulated in every frame, so the overlap can be told from geometry: each person's region in a view is drawn as
capsules around the bones between their projected targets (radii in metres, ``BONE_RADII``, scaled by focal length
over depth) and a filled torso.

* A view where other people's regions cover more than ``OVERLAP_SHARE`` of the followed person's is left out of the
  body fit, the training and the evaluation, as views showing only somebody else are: in front, they hide the
  person; behind, the one mask covers both and the view's detection and mask may be theirs (measured on
  Demo_MultiPerson: docs/results/real-capture.md, *Other people in view*).
* In the views kept, the mask loses its pixels outside the followed person's fitted body that lie nearer the other
  people's regions than that body (:func:`without_others`): what lies there is somebody else.
* Where somebody else's capsule is nearer the camera than the followed person's at a pixel of the followed person's
  neighbourhood (bone by bone, :func:`body_depth`), the pixels' owner is unknown (:func:`hidden_region`): the
  capture marks them in ``mask_unknown/`` (docs/formats.md §1.5), no loss draws them, the body fits let the body
  lie there, and the evaluation counts them with the boundary band, in the background's colour.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipelines.body.silhouettes import distance_to_mask
from pipelines.datasets.camera import Camera, project_distorted
from pipelines.datasets.keypoints import TARGET_NAMES

#: a view is left out when other people's regions cover more than this share of the followed person's region
OVERLAP_SHARE = 0.25
#: (target, target, radius in metres) of each capsule drawn for a person: limbs, the torso's sides, the head
BONE_RADII = (
    ("l_hip", "l_knee", 0.08),
    ("l_knee", "l_ankle", 0.06),
    ("l_ankle", "l_foot", 0.05),
    ("r_hip", "r_knee", 0.08),
    ("r_knee", "r_ankle", 0.06),
    ("r_ankle", "r_foot", 0.05),
    ("l_shoulder", "l_elbow", 0.06),
    ("l_elbow", "l_wrist", 0.05),
    ("r_shoulder", "r_elbow", 0.06),
    ("r_elbow", "r_wrist", 0.05),
    ("l_shoulder", "l_hip", 0.08),
    ("r_shoulder", "r_hip", 0.08),
    ("l_shoulder", "r_shoulder", 0.06),
    ("l_hip", "r_hip", 0.08),
    ("pelvis", "neck", 0.12),
    ("neck", "head", 0.1),
)
#: pieces each bone is cut in along its length for :func:`body_depth` (a thigh reaching back spans 60 cm of depth)
DEPTH_PIECES = 4
#: the torso's quadrilateral, filled between the capsules of its sides
TORSO = ("l_shoulder", "r_shoulder", "r_hip", "l_hip")


def body_neighbourhood(body: np.ndarray, margin_fraction: float = 0.04) -> np.ndarray:
    """(H, W) bool: the pixels within ``margin_fraction`` of the image height of the (H, W) bool ``body``."""
    if not body.any():
        return np.zeros_like(body)
    return distance_to_mask(body) <= max(1.0, margin_fraction * body.shape[0])


def _index(name: str) -> int:
    return TARGET_NAMES.index(name)


def _capsules(camera: Camera, points: np.ndarray, pieces: int = 1):
    """The person ``points`` (T, 3 world targets, NaN where missing) in ``camera``'s distorted pixels: a list of
    (depth, kind, pixels, width) with kind "line" (two (2,) int ends, ``BONE_RADII``' capsule width 2 r f_y / z at
    its joints' mean depth z; each bone cut in ``pieces`` along its length, each at the depth of its middle) or
    "torso" (the filled quadrilateral at its corners' mean depth, width 0). Targets behind the camera or missing
    leave their shapes out."""
    in_camera = points @ camera.cam_from_world[:3, :3].T + camera.cam_from_world[:3, 3]
    depth = in_camera[:, 2]
    ok = np.isfinite(in_camera).all(-1) & (depth > 1e-3)
    pixels = np.full((len(points), 2), np.nan)
    pixels[ok] = project_distorted(camera, points[ok])
    ok &= (np.abs(pixels) < 1e5).all(-1)
    shapes = []
    for a, b, radius in BONE_RADII:
        i, j = _index(a), _index(b)
        if ok[i] and ok[j]:
            width = max(1, int(round(2 * radius * camera.K[1, 1] / (0.5 * (depth[i] + depth[j])))))
            t = np.linspace(0.0, 1.0, pieces + 1)[:, None]  # the bone cut in pieces, each at its middle's depth
            ends = np.round((1 - t) * pixels[i] + t * pixels[j]).astype(np.int32)
            middles = (1 - (t[:-1, 0] + t[1:, 0]) / 2) * depth[i] + (t[:-1, 0] + t[1:, 0]) / 2 * depth[j]
            shapes.extend((float(z), "line", ends[k : k + 2], width) for k, z in enumerate(middles))
    corners = [_index(n) for n in TORSO]
    if ok[corners].all():
        shapes.append((float(depth[corners].mean()), "torso", np.round(pixels[corners]).astype(np.int32), 0))
    return shapes


def _draw(image: np.ndarray, shape, value: float, origin: tuple[int, int] = (0, 0)) -> None:
    """Draw one of :func:`_capsules`' shapes into ``image``, whose pixel (0, 0) is the image's (row, col) ``origin``."""
    _, kind, pixels, width = shape
    pixels = pixels - np.array([origin[1], origin[0]], np.int32)
    if kind == "line":
        cv2.line(image, tuple(map(int, pixels[0])), tuple(map(int, pixels[1])), value, width, cv2.LINE_8)
    else:
        cv2.fillConvexPoly(image, pixels, value)


def body_region(camera: Camera, points: np.ndarray, box: tuple[slice, slice] | None = None) -> np.ndarray:
    """(H, W) bool: the person ``points`` (T, 3 world targets, NaN where missing) drawn in ``camera``'s image as
    capsules of ``BONE_RADII`` (a capsule's width in pixels is 2 r f_y / z at its joints' mean depth z) and the filled
    torso, in distorted pixels (as the masks are). Targets behind the camera or missing leave their capsules out.
    With ``box`` (row and column slices), only that part of the image."""
    rows, cols = box or (slice(0, camera.height), slice(0, camera.width))
    region = np.zeros((rows.stop - rows.start, cols.stop - cols.start), np.uint8)
    for shape in _capsules(camera, points):
        _draw(region, shape, 1, (rows.start, cols.start))
    return region > 0


def body_depth(camera: Camera, points: np.ndarray, box: tuple[slice, slice] | None = None) -> np.ndarray:
    """(H, W) float32: over :func:`body_region`, the depth of the nearest capsule or torso covering each pixel (each
    bone drawn in ``DEPTH_PIECES`` pieces along its length at their middles' depths, the farthest first); inf
    elsewhere. With ``box`` (row and column slices), only that part of the image."""
    region = body_region(camera, points, box)
    depth = np.full(region.shape, np.inf, np.float32)
    origin = (box[0].start, box[1].start) if box else (0, 0)
    for z, kind, pixels, width in sorted(_capsules(camera, points, DEPTH_PIECES), key=lambda s: -s[0]):
        _draw(depth, (z, kind, pixels, width + 2 if width else 0), float(z), origin)  # 1 px wider: the ends round
    depth[~region] = np.inf
    return depth


def overlap_share(camera: Camera, points: np.ndarray, others: list[np.ndarray]) -> float:
    """Share of the person ``points``' :func:`body_region` in ``camera`` that the regions of ``others`` (each (T, 3)
    targets) cover, whoever stands in front (0 when the person is not in the image)."""
    region = body_region(camera, points)
    area = int(region.sum())
    if area == 0 or not others:
        return 0.0
    covered = np.logical_or.reduce([body_region(camera, o) for o in others])
    return float((covered & region).sum() / area)


def without_others(mask: np.ndarray, body: np.ndarray, camera: Camera, others: list[np.ndarray]) -> np.ndarray:
    """(H, W) bool ``mask`` less its pixels outside ``body`` ((H, W) bool, the followed person's fitted silhouette)
    that lie nearer the :func:`body_region` of one of ``others`` ((T, 3) targets) than ``body``: the capsules are
    thinner than a person (hair, clothes), so what the one mask holds beside them, on their side, is theirs too.
    ``camera`` of the mask's size."""
    if not others:
        return mask
    covered = np.logical_or.reduce([body_region(camera, o) for o in others])
    if not covered.any():
        return mask
    decide = mask & ~body & ~covered
    if not body.any() or not decide.any():
        return mask & ~(covered & ~body)
    # the distances within boxes, not the whole image: the box around the body and the pixels to decide gives their
    # exact distances to the body; grown by the largest of those, it holds every covered pixel nearer to one of them
    # than the body (farther ones could not win), so the comparison is the whole image's
    box = _box(decide | body)
    to_body = distance_to_mask(body[box])
    grown = _box(decide | body, int(np.ceil(to_body[decide[box]].max())) + 1)
    within = tuple(slice(b.start - g.start, b.stop - g.start) for b, g in zip(box, grown))  # box inside grown
    theirs = np.zeros_like(mask)
    theirs[box] = decide[box] & (distance_to_mask(covered[grown])[within] < to_body)
    return mask & ~((theirs | covered) & ~body)


def _box(region: np.ndarray, pad: int = 0) -> tuple[slice, slice]:
    """Row and column slices of the bounding box of the (H, W) bool ``region`` (not empty), grown by ``pad`` pixels
    on every side within the image."""
    rows, cols = np.nonzero(region.any(axis=1))[0], np.nonzero(region.any(axis=0))[0]
    return (
        slice(max(0, rows[0] - pad), min(region.shape[0], rows[-1] + 1 + pad)),
        slice(max(0, cols[0] - pad), min(region.shape[1], cols[-1] + 1 + pad)),
    )


def _centre_depth(camera: Camera, points: np.ndarray) -> float:
    """Depth along ``camera``'s axis of the median of the finite ``points`` (inf when none is finite)."""
    finite = points[np.isfinite(points).all(-1)]
    if not len(finite):
        return np.inf
    return float(camera.cam_from_world[2, :3] @ np.median(finite, axis=0) + camera.cam_from_world[2, 3])


def hidden_region(camera: Camera, points: np.ndarray, others: list[np.ndarray], near: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels within ``near`` (H, W) bool (the person's neighbourhood) where the :func:`body_region`
    of one of ``others`` ((T, 3) targets) lies nearer ``camera`` than the person ``points``: than the person's own
    capsule there (:func:`body_depth`; a leg behind somebody else's), or than the person's centre outside them."""
    hidden = np.zeros_like(near)
    if not others or not near.any():
        return hidden
    box = _box(near)
    theirs = np.minimum.reduce([body_depth(camera, o, box) for o in others])
    mine = body_depth(camera, points, box)
    mine[np.isinf(mine)] = _centre_depth(camera, points)
    hidden[box] = (theirs < mine) & near[box]
    return hidden


def person_mask(
    raw: np.ndarray, body: np.ndarray, camera: Camera, points: np.ndarray, others: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """The followed person's mask and the pixels of unknown owner, both (H, W) bool, from a view's ``raw`` segmenter
    mask: the raw mask within the fitted ``body``'s neighbourhood (``body_neighbourhood``), less the others
    outside the body (:func:`without_others`) and less the unknown pixels (:func:`hidden_region`). ``points``: the
    person's (T, 3) targets; ``others``: the other people's; ``camera`` of the masks' size."""
    near = body_neighbourhood(body)
    unknown = hidden_region(camera, points, others, near)
    return without_others(raw & near, body, camera, others) & ~unknown, unknown


def leave_out_overlapped(cameras: list[Camera], found) -> list[int]:
    """Mark as unused (``found.used``) each used view of ``found`` (``pipelines.prepare.people.targets.Triangulated``)
    where the other people of its frame (``found.others``) cover more than ``OVERLAP_SHARE`` of the person
    (:func:`overlap_share`); their keypoints' confidences become 0 (the detector may have found somebody else).
    Returns the number of views left out per camera, also added to ``found.view_notes[v]["overlapped"]``."""
    count = [0] * len(cameras)
    for i, frame in enumerate(found.frames):
        others = found.others.get(frame, [])
        for v, camera in enumerate(cameras):
            if others and found.used[i, v] and overlap_share(camera, found.points[i], others) > OVERLAP_SHARE:
                found.used[i, v] = False
                found.keypoints[i, v, :, 2] = 0.0
                count[v] += 1
    for v, n in enumerate(count):
        found.view_notes[v]["overlapped"] += n
    return count
