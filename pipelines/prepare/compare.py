"""Two preparations of one recording side by side (``python -m pipelines.prepare.compare A B``): how well each body
agrees with its keypoints and masks (report.json: reprojection, IoU, flagged cameras) and how far the two fitted
bodies lie apart, frame by frame (vertices/<frame>.npy, world metres). Used to check one detector's keypoints
against another's (docs/results/real-capture.md)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from pipelines.datasets.errors import CaptureError


def _report(capture: Path) -> dict:
    path = capture / "report.json"
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise CaptureError(f"{path}: not a prepared capture's report ({err})") from None


def _vertices(capture: Path, frame: int) -> np.ndarray:
    path = capture / "vertices" / f"{frame}.npy"
    if not path.is_file():
        raise CaptureError(f"{path}: missing (both captures must hold the frame)")
    return np.load(path, allow_pickle=False).astype(np.float64)


def compare_captures(a: Path, b: Path) -> dict:
    """Each capture's fit quality (report summary, per-camera reprojection and IoU, flags) and the distance between
    the two bodies over the frames both kept: per frame the mean vertex distance, then its median, mean and
    95th percentile over frames (cm)."""
    reports = [(str(p), _report(Path(p))) for p in (a, b)]  # a list: a capture may be compared with itself
    # source frame -> the capture's frame number, per capture
    index = [{f: i for i, f in enumerate(r["frames"]["source_frames"])} for _, r in reports]
    shared = sorted(set(index[0]) & set(index[1]))
    if not shared:
        raise CaptureError(f"{a}, {b}: no frame in common")
    distance = [
        100 * np.linalg.norm(_vertices(Path(a), index[0][f]) - _vertices(Path(b), index[1][f]), axis=1).mean()
        for f in shared
    ]
    fit = {
        name: {
            **r["summary"],
            "flagged": r.get("flagged_cameras", {}),
            "cameras": {
                cam: {"reprojection_pct_height": c.get("body_reprojection_pct_height"), "iou": c.get("iou_mean")}
                for cam, c in r["cameras"].items()
            },
        }
        for name, r in reports
    }
    body = {"frames": len(shared), "median_cm": float(np.median(distance)), "mean_cm": float(np.mean(distance))}
    return {"fit": fit, "body_distance": body | {"p95_cm": float(np.percentile(distance, 95))}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipelines.prepare.compare", description=__doc__)
    parser.add_argument("first", type=Path, help="a capture written by narf-prepare-capture")
    parser.add_argument("second", type=Path, help="another preparation of the same recording")
    args = parser.parse_args(argv)
    print(json.dumps(compare_captures(args.first, args.second), indent=1))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except CaptureError as err:
        print(f"compare: error: {err}", file=sys.stderr)
        sys.exit(2)
