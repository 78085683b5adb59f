"""Person keypoints from detectors, and the body-model joints they stand for (docs/formats.md §9).

Layouts read: OpenPose BODY_25, BODY_25B (Pose2Sim's OpenPose default) and COCO-18, MMPose / RTMPose COCO-17 and
HALPE_26 (Pose2Sim >= 0.9), all in OpenPose's JSON (one file per frame and camera), and BlazePose's 33 landmarks.
Each is mapped onto one set of **targets**: SMPL joints that the body fit matches (:data:`TARGETS`). A target may
average several keypoints (the ears for the head); keypoints that are not joint centres (hips, shoulders, neck,
head) get a learned offset in the body fit. BODY_25 and BODY_25B have the same size: :func:`layout_of_25` tells them
apart from the points themselves, and never guesses.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fitting.files import atomic_write_bytes
from pipelines.datasets.errors import CaptureError

LAYOUT_SIZES = {"body25": 25, "body25b": 25, "coco18": 18, "coco17": 17, "halpe26": 26, "blazepose": 33}
#: The layouts of OpenPose-style JSON files, by their number of points (25 is checked: :func:`layout_of_25`).
FILE_LAYOUTS = {17: ("coco17",), 18: ("coco18",), 25: ("body25", "body25b"), 26: ("halpe26",)}
LAYOUT_NAMES = {
    "body25": "OpenPose BODY_25",
    "body25b": "OpenPose BODY_25B",
    "coco18": "OpenPose COCO-18",
    "coco17": "COCO-17",
    "halpe26": "HALPE_26",
    "blazepose": "BlazePose",
}
#: What tells each 25-point layout (:func:`layout_of_25`).
LAYOUT_HINTS = {"body25": "point 1, the neck, lies between the shoulders", "body25b": "points 1-2 sit beside the nose"}


@dataclass(frozen=True)
class Target:
    """A body-model joint the fit matches, with the keypoints of each layout that stand for it.

    Attributes:
        name: e.g. ``l_knee``.
        joint: SMPL joint index.
        sources: layout -> keypoint indices averaged (absent: the layout has no such point).
        weight: relative weight in the fit (points that are not joint centres weigh less).
        offset: the detector's point sits off the joint centre; the fit learns a constant offset (mirrored left /
            right) in the joint's frame.
    """

    name: str
    joint: int
    sources: dict
    weight: float = 1.0
    offset: bool = False


def _coco17(*points: int) -> dict:
    """The same points in the three layouts that begin with COCO-17's 17 (BODY_25B, HALPE_26, COCO-17)."""
    return {layout: points for layout in ("body25b", "halpe26", "coco17")}


TARGETS = (
    Target("pelvis", 0, {"body25": (8,), "halpe26": (19,)}, 0.5, True),
    Target("l_hip", 1, {"body25": (12,), "coco18": (11,), "blazepose": (23,), **_coco17(11)}, 0.7, True),
    Target("r_hip", 2, {"body25": (9,), "coco18": (8,), "blazepose": (24,), **_coco17(12)}, 0.7, True),
    Target("l_knee", 4, {"body25": (13,), "coco18": (12,), "blazepose": (25,), **_coco17(13)}),
    Target("r_knee", 5, {"body25": (10,), "coco18": (9,), "blazepose": (26,), **_coco17(14)}),
    Target("l_ankle", 7, {"body25": (14,), "coco18": (13,), "blazepose": (27,), **_coco17(15)}),
    Target("r_ankle", 8, {"body25": (11,), "coco18": (10,), "blazepose": (28,), **_coco17(16)}),
    Target("l_foot", 10, {"body25": (19, 20), "body25b": (19, 20), "halpe26": (20, 22), "blazepose": (31,)}, 0.5, True),
    Target("r_foot", 11, {"body25": (22, 23), "body25b": (22, 23), "halpe26": (21, 23), "blazepose": (32,)}, 0.5, True),
    Target(
        "neck",
        12,
        {"body25": (1,), "body25b": (17,), "coco18": (1,), "halpe26": (18,), "blazepose": (11, 12)},
        0.3,
        True,
    ),
    Target("head", 15, {"body25": (17, 18), "coco18": (16, 17), "blazepose": (7, 8), **_coco17(3, 4)}, 0.5, True),
    Target("l_shoulder", 16, {"body25": (5,), "coco18": (5,), "blazepose": (11,), **_coco17(5)}, 0.7, True),
    Target("r_shoulder", 17, {"body25": (2,), "coco18": (2,), "blazepose": (12,), **_coco17(6)}, 0.7, True),
    Target("l_elbow", 18, {"body25": (6,), "coco18": (6,), "blazepose": (13,), **_coco17(7)}),
    Target("r_elbow", 19, {"body25": (3,), "coco18": (3,), "blazepose": (14,), **_coco17(8)}),
    Target("l_wrist", 20, {"body25": (7,), "coco18": (7,), "blazepose": (15,), **_coco17(9)}),
    Target("r_wrist", 21, {"body25": (4,), "coco18": (4,), "blazepose": (16,), **_coco17(10)}),
)
TARGET_NAMES = tuple(t.name for t in TARGETS)
TARGET_JOINTS = tuple(t.joint for t in TARGETS)


def mirror_index(index: int) -> int:
    """Index of the left/right mirror of target ``index`` (itself for central targets)."""
    name = TARGETS[index].name
    swapped = {"l": "r", "r": "l"}.get(name[:1]) if name[1:2] == "_" else None
    return TARGET_NAMES.index(swapped + name[1:]) if swapped else index


def to_targets(keypoints: np.ndarray, layout: str) -> np.ndarray:
    """Keypoints of a layout -> targets: the mean position of each target's keypoints and their least confidence.

    Args:
        keypoints: (..., K, 3) x, y, confidence (0 = not seen).
        layout: ``body25``, ``coco18`` or ``blazepose``.

    Returns:
        (..., T, 3) with T = ``len(TARGETS)``; confidence 0 where the layout has no such point.
    """
    out = np.zeros(keypoints.shape[:-2] + (len(TARGETS), 3), np.float64)
    for t, target in enumerate(TARGETS):
        sources = target.sources.get(layout)
        if not sources:
            continue
        picked = keypoints[..., list(sources), :]
        out[..., t, :2] = picked[..., :2].mean(axis=-2)
        out[..., t, 2] = picked[..., 2].min(axis=-1)
    return out


_FRAME = re.compile(r"(\d+)(?=_keypoints\.json$)")


def frame_number(path: Path) -> int:
    """The frame number of an OpenPose file name (``cam01_000000000012_keypoints.json`` -> 12)."""
    match = _FRAME.search(Path(path).name) or re.search(r"(\d+)(?!.*\d)", Path(path).stem)
    if match is None:
        raise CaptureError(f"{path}: no frame number in the file name")
    return int(match.group(1))


def read_openpose(path: Path) -> list[np.ndarray]:
    """People of one OpenPose-style JSON file: a list of (K, 3) arrays (x, y, confidence), K the same for all and
    one of :data:`FILE_LAYOUTS`. Confidences must lie in [0, 1]. An entry whose ``pose_keypoints_2d`` is empty is no
    person and is skipped."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        people = data["people"]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as err:
        raise CaptureError(f"{path}: not an OpenPose keypoint file ({type(err).__name__}: {err})") from None
    found = []
    for p, person in enumerate(people if isinstance(people, list) else [None]):
        try:
            flat = np.asarray(person["pose_keypoints_2d"], dtype=np.float64)
        except (TypeError, KeyError, ValueError):
            raise CaptureError(f"{path}: people[{p}] has no numeric pose_keypoints_2d") from None
        if flat.size == 0:  # OpenPose writes such entries (a person found by other parts only): no person here
            continue
        if flat.ndim != 1 or flat.size % 3 or flat.size // 3 not in FILE_LAYOUTS:
            sizes = ", ".join(f"{3 * k} ({'/'.join(v)})" for k, v in FILE_LAYOUTS.items())
            raise CaptureError(f"{path}: people[{p}] has {flat.size} values in pose_keypoints_2d; expected {sizes}")
        if not np.isfinite(flat).all():
            raise CaptureError(f"{path}: people[{p}] pose_keypoints_2d holds NaN or infinite values")
        points = flat.reshape(-1, 3)
        if found and len(points) != len(found[0]):
            raise CaptureError(f"{path}: people[{p}] has {len(points)} points where people[0] has {len(found[0])}")
        if ((points[:, 2] < 0) | (points[:, 2] > 1)).any():
            raise CaptureError(f"{path}: people[{p}] has confidences outside [0, 1]")
        found.append(points)
    return found


def layout_of_25(people: list[np.ndarray], seen: float = 0.3) -> str | None:
    """BODY_25 or BODY_25B, from 25-point people (each (25, 3)), or None when the points cannot tell.

    Two tests, each on the points it needs seen (confidence >= ``seen``): *head* (BODY_25B: points 1-4 are the eyes
    and ears, all within half a shoulder width, points 5-6, of the nose 0; in BODY_25 they are the neck and the right
    arm) and *neck* (BODY_25: point 1 lies within a quarter of the shoulder width, points 2-5, of the shoulders'
    midpoint). A person passing exactly one votes for its layout; the layout is told when at least 3 people vote and
    90 % of the votes agree."""
    votes = {"body25": 0, "body25b": 0}
    for points in people:
        xy, ok = points[:, :2], points[:, 2] >= seen
        head = neck = False
        seen_head = [i for i in (1, 2, 3, 4) if ok[i]]
        if ok[[0, 5, 6]].all() and len(seen_head) >= 2:
            width = np.linalg.norm(xy[5] - xy[6])
            head = width > 0 and max(np.linalg.norm(xy[i] - xy[0]) for i in seen_head) < width / 2
        if ok[[1, 2, 5]].all():
            width = np.linalg.norm(xy[2] - xy[5])
            neck = width > 0 and np.linalg.norm(xy[1] - (xy[2] + xy[5]) / 2) < width / 4
        if head != neck:
            votes["body25b" if head else "body25"] += 1
    total = sum(votes.values())
    best = max(votes, key=votes.get)
    return best if total >= 3 and votes[best] >= 0.9 * total else None


#: Points of each file layout on the face (nose, eyes; HALPE's head), where a synthetic writer puts the head joint.
FACE_POINTS = {
    "body25": (0, 15, 16),
    "body25b": (0, 1, 2),
    "coco18": (0, 14, 15),
    "coco17": (0, 1, 2),
    "halpe26": (0, 1, 2, 17),
}


def keypoints_from_joints(pixels: np.ndarray, layout: str, confidence: float = 0.9) -> np.ndarray:
    """(24, 2) projected SMPL joints -> (K, 3) keypoints of ``layout``, as synthetic detections: each point a target
    reads is placed on the target's joint (both ears on the head joint, both toes on the foot joint), the face's
    points on the head joint; the others are not seen (c = 0)."""
    keypoints = np.zeros((LAYOUT_SIZES[layout], 3))
    for index in FACE_POINTS.get(layout, ()):
        keypoints[index] = (*pixels[15], confidence)
    for target in TARGETS:
        for index in target.sources.get(layout, ()):
            keypoints[index] = (*pixels[target.joint], confidence)
    return keypoints


def write_openpose(path: Path, people: list[np.ndarray]) -> None:
    """Write people ((K, 3) arrays) as an OpenPose JSON file (version 1.3 layout), atomically."""
    entries = [{"person_id": [-1], "pose_keypoints_2d": [round(float(v), 3) for v in p.reshape(-1)]} for p in people]
    atomic_write_bytes(Path(path), json.dumps({"version": 1.3, "people": entries}).encode())
