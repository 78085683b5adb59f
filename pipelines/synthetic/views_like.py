"""A capture seen as another rig sees its person (docs/guides/synthetic-data.md, *A rig's views on exact data*).

``python -m pipelines.synthetic.views_like SOURCE LIKE OUT`` writes OUT: SOURCE's files (hard links) with a
``splits.json`` that trains on the cameras of SOURCE standing where LIKE's training cameras stand around their
person, seen from the held-out camera, and holds out SOURCE's last frames in LIKE's proportion. With SOURCE a
synthetic capture (exact bodies, cameras and masks) and LIKE a prepared recording, the two fit the same views of a
person: what the recording loses beyond the synthetic capture is its inputs', not the model's.

Where each camera stands is its azimuth about the rig's vertical (the normal of the plane through the camera
centres), seen from the point that the cameras' optical axes pass nearest (the person, for a rig aimed at one).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.errors import CaptureError
from pipelines.synthetic.staging import link_into, publish, start_staging

DATASET = "views_like"


def axes_meeting_point(centres: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """The point nearest every camera's optical axis in the least-squares sense: argmin_x sum_i |(I - a_i a_i^T)(x -
    c_i)|^2, i.e. sum_i (I - a_i a_i^T) x = sum_i (I - a_i a_i^T) c_i. centres, axes: (C, 3), axes unit. -> (3,)."""
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]  # (C, 3, 3)
    return np.linalg.solve(projectors.sum(0), np.einsum("cij,cj->i", projectors, centres))


def rig_azimuths(cam_from_world: np.ndarray, vertical: np.ndarray | None = None) -> np.ndarray:
    """Each camera's azimuth (degrees, (C,)) about the vertical through the point its axes meet, measured from the
    first camera. ``vertical`` (3,): the world's up (a capture's floor); None: the normal of the plane through the
    camera centres (a rig at one height), its sign that of the cameras' mean up (-y of each camera), so that two
    rigs' azimuths turn the same way. cam_from_world: (C, 4, 4), C >= 2 (3 without ``vertical``)."""
    rotations = cam_from_world[:, :3, :3]
    centres = -np.einsum("cji,cj->ci", rotations, cam_from_world[:, :3, 3])  # -R^T t
    axes = rotations[:, 2, :]  # the optical axis (+z of the camera) in the world
    meeting = axes_meeting_point(centres, axes)
    if vertical is None:
        vertical = np.linalg.svd(centres - centres.mean(0))[2][-1]
    vertical = np.asarray(vertical, float) / np.linalg.norm(vertical)
    if np.dot(vertical, -rotations[:, 1, :].mean(0)) < 0:
        vertical = -vertical
    offsets = centres - meeting
    flat = offsets - np.outer(offsets @ vertical, vertical)
    reference = flat[0] / np.linalg.norm(flat[0])
    side = np.cross(vertical, reference)
    return np.degrees(np.arctan2(flat @ side, flat @ reference))


def matching_views(like_azimuths, like_train, like_test: int, azimuths, test: int) -> list[int]:
    """The cameras of a rig (``azimuths``) standing, relative to its camera ``test``, where ``like_train`` stand
    relative to ``like_test`` in the other rig: for each, the nearest in azimuth, each camera used once."""
    taken, chosen = {test}, []
    for camera in like_train:
        wanted = like_azimuths[camera] - like_azimuths[like_test] + azimuths[test]
        gap = np.abs((np.asarray(azimuths) - wanted + 180) % 360 - 180)
        best = min((g, c) for c, g in enumerate(gap) if c not in taken)[1]
        taken.add(best)
        chosen.append(best)
    return chosen


def views_like(source: Path, like: Path, out: Path, test_camera: int = 0) -> dict:
    """Write OUT (see the module's docstring); returns its splits (with the matched azimuths)."""
    source_capture, like_capture = ZjuCapture(source), ZjuCapture(like)
    like_protocol = like_capture.protocol("narf")
    if len(like_protocol.test_views) != 1:
        raise CaptureError(f"{like}: needs exactly one held-out camera (it has {len(like_protocol.test_views)})")
    if not 0 <= test_camera < source_capture.n_cameras:
        raise CaptureError(f"{source}: has no camera {test_camera} ({source_capture.n_cameras} cameras)")
    like_azimuths = rig_azimuths(np.stack([c.cam_from_world for c in like_capture.cameras]), _up(like_capture))
    azimuths = rig_azimuths(np.stack([c.cam_from_world for c in source_capture.cameras]), _up(source_capture))
    train = matching_views(like_azimuths, like_protocol.train_views, like_protocol.test_views[0], azimuths, test_camera)
    share = len(like_protocol.train_frames) / (len(like_protocol.train_frames) + len(like_protocol.novel_frames))
    n_train = max(1, round(share * source_capture.n_frames))
    splits = {
        "train_frames": list(range(n_train)),
        "novel_frames": list(range(n_train, source_capture.n_frames)),
        "train_views": train,
        "test_views": [test_camera],
        "excluded": [],
    }
    partial = start_staging(out, DATASET, "capture with another rig's views")
    for path in Path(source).iterdir():
        if path.name in ("splits.json", "synthetic.json"):
            continue
        link_into(path, partial / path.name)
    (partial / "splits.json").write_text(json.dumps(splits, indent=1))
    relative = {
        "like": [
            round(float(like_azimuths[c] - like_azimuths[like_protocol.test_views[0]]), 1)
            for c in like_protocol.train_views
        ],
        "source": [round(float(azimuths[c] - azimuths[test_camera]), 1) for c in train],
    }
    publish(partial, out, {"dataset": DATASET, "source": str(source), "like": str(like), "azimuths": relative})
    return {**splits, "azimuths": relative}


def _up(capture: ZjuCapture) -> np.ndarray | None:
    """The capture's up (its floor's normal, ``floor.json``), or None when it has no floor."""
    return None if capture.floor is None else capture.floor.up


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m pipelines.synthetic.views_like", description=__doc__.split("\n\n")[1]
    )
    parser.add_argument("source", type=Path, help="the capture whose files are used (e.g. data/synthetic/taichi)")
    parser.add_argument("like", type=Path, help="the capture whose rig is copied (e.g. data/real/demo_single_person)")
    parser.add_argument("out", type=Path, help="the new capture's folder")
    parser.add_argument("--test-camera", type=int, default=0, help="SOURCE's camera that is held out (default 0)")
    args = parser.parse_args(argv)
    try:
        splits = views_like(args.source, args.like, args.out, args.test_camera)
    except (CaptureError, FileExistsError, OSError) as err:
        print(f"views_like: {err}", file=sys.stderr)
        return 2
    angles, test = splits["azimuths"], splits["test_views"][0]
    print(f"{args.out}: training views {splits['train_views']} at {angles['source']} degrees from view {test}")
    print(f"  (the rig copied: {angles['like']}); {len(splits['train_frames'])} training frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
