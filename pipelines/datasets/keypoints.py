"""Person keypoints from detectors, and the body-model joints they stand for (docs/formats.md §9).

Three layouts are read: OpenPose BODY_25 and COCO-18 (``<name>_<frame:012d>_keypoints.json``, one file per frame
and camera) and BlazePose's 33 landmarks. Each is mapped onto one set of **targets**: SMPL joints that the body fit
matches (:data:`TARGETS`). A target may average several keypoints (the ears for the head); keypoints that are not
joint centres (hips, shoulders, neck, head) get a learned offset in the body fit.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipelines.datasets.smpl_files import atomic_write_bytes
from pipelines.datasets.zju_mocap import CaptureError

LAYOUT_SIZES = {"body25": 25, "coco18": 18, "blazepose": 33}


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


TARGETS = (
    Target("pelvis", 0, {"body25": (8,)}, 0.5, True),
    Target("l_hip", 1, {"body25": (12,), "coco18": (11,), "blazepose": (23,)}, 0.7, True),
    Target("r_hip", 2, {"body25": (9,), "coco18": (8,), "blazepose": (24,)}, 0.7, True),
    Target("l_knee", 4, {"body25": (13,), "coco18": (12,), "blazepose": (25,)}),
    Target("r_knee", 5, {"body25": (10,), "coco18": (9,), "blazepose": (26,)}),
    Target("l_ankle", 7, {"body25": (14,), "coco18": (13,), "blazepose": (27,)}),
    Target("r_ankle", 8, {"body25": (11,), "coco18": (10,), "blazepose": (28,)}),
    Target("l_foot", 10, {"body25": (19, 20), "blazepose": (31,)}, 0.5, True),
    Target("r_foot", 11, {"body25": (22, 23), "blazepose": (32,)}, 0.5, True),
    Target("neck", 12, {"body25": (1,), "coco18": (1,), "blazepose": (11, 12)}, 0.3, True),
    Target("head", 15, {"body25": (17, 18), "coco18": (16, 17), "blazepose": (7, 8)}, 0.5, True),
    Target("l_shoulder", 16, {"body25": (5,), "coco18": (5,), "blazepose": (11,)}, 0.7, True),
    Target("r_shoulder", 17, {"body25": (2,), "coco18": (2,), "blazepose": (12,)}, 0.7, True),
    Target("l_elbow", 18, {"body25": (6,), "coco18": (6,), "blazepose": (13,)}),
    Target("r_elbow", 19, {"body25": (3,), "coco18": (3,), "blazepose": (14,)}),
    Target("l_wrist", 20, {"body25": (7,), "coco18": (7,), "blazepose": (15,)}),
    Target("r_wrist", 21, {"body25": (4,), "coco18": (4,), "blazepose": (16,)}),
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


def read_openpose(path: Path) -> tuple[list[np.ndarray], str]:
    """People of one OpenPose JSON file: a list of (K, 3) arrays (x, y, confidence) and the layout name."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        people = data["people"]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as err:
        raise CaptureError(f"{path}: not an OpenPose keypoint file ({type(err).__name__}: {err})") from None
    found, layout = [], None
    for p, person in enumerate(people if isinstance(people, list) else [None]):
        try:
            flat = np.asarray(person["pose_keypoints_2d"], dtype=np.float64)
        except (TypeError, KeyError, ValueError):
            raise CaptureError(f"{path}: people[{p}] has no numeric pose_keypoints_2d") from None
        joints = flat.size // 3
        sizes = {v: k for k, v in LAYOUT_SIZES.items() if k != "blazepose"}
        if flat.ndim != 1 or flat.size % 3 or joints not in sizes:
            raise CaptureError(
                f"{path}: people[{p}] has {flat.size} values in pose_keypoints_2d; expected 75 (BODY_25) or 54 (COCO)"
            )
        if not np.isfinite(flat).all():
            raise CaptureError(f"{path}: people[{p}] pose_keypoints_2d holds NaN or infinite values")
        layout = sizes[joints]
        found.append(flat.reshape(joints, 3))
    return found, layout or "body25"


def write_openpose(path: Path, people: list[np.ndarray]) -> None:
    """Write people ((K, 3) arrays) as an OpenPose JSON file (version 1.3 layout), atomically."""
    entries = [{"person_id": [-1], "pose_keypoints_2d": [round(float(v), 3) for v in p.reshape(-1)]} for p in people]
    atomic_write_bytes(Path(path), json.dumps({"version": 1.3, "people": entries}).encode())
