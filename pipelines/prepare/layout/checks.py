"""What a user checks before training: the fitted body drawn over every camera's frames, its silhouette against
the person mask (IoU), and the reprojection errors per camera and per joint, with cameras that disagree flagged.
"""

from __future__ import annotations

import cv2
import numpy as np

#: a camera is flagged when its median reprojection error exceeds this fraction of the image height and stands this
#: many times above the median of the other cameras (cameras that all agree at a poor figure are a warning about the
#: capture, :func:`reprojection_notice`, not a fault of each) ...
FLAG_ERROR, FLAG_ABOVE = 0.015, 1.2
#: ... or exceeds this many times the median of the other cameras, whatever its size
FLAG_RATIO = 2.5
#: and when its body-vs-mask IoU is below this
FLAG_IOU = 0.6
#: or when its person disagrees with the other cameras in more than this fraction of the frames
FLAG_DISAGREED = 0.2
#: or when the body fit had to turn it by more than this many degrees or move it by more than this many cm
FLAG_TURN, FLAG_SHIFT = 2.0, 3.0


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def draw_overlay(
    bgr: np.ndarray, body: np.ndarray, detected: np.ndarray | None, fitted: np.ndarray, seen: bool
) -> np.ndarray:
    """The frame with the body's silhouette tinted, detected keypoints (green; grey where the view was not used)
    and the fitted targets (red) drawn."""
    out = bgr.copy()
    tint = np.array([40, 40, 220] if seen else [160, 160, 160], np.float32)
    out[body] = (0.55 * out[body] + 0.45 * tint).astype(np.uint8)
    radius = max(2, bgr.shape[0] // 200)
    if detected is not None:
        for x, y, c in detected:
            if c > 0 and np.isfinite([x, y]).all():
                cv2.circle(out, (int(x), int(y)), radius + 1, (0, 200, 0) if seen else (128, 128, 128), -1)
    for x, y in fitted:
        if np.isfinite([x, y]).all():
            cv2.circle(out, (int(x), int(y)), radius, (0, 0, 255), -1)
    return out


def _flag_threshold(typical: float) -> float:
    """The reprojection error above which a camera is flagged, given the other cameras' median ``typical`` (NaN:
    no other camera to compare with, so the absolute threshold alone)."""
    if not np.isfinite(typical):
        return FLAG_ERROR
    return min(FLAG_RATIO * typical, max(FLAG_ERROR, FLAG_ABOVE * typical))


def reprojection_notice(errors: dict[str, float]) -> str | None:
    """A warning when the cameras' typical median reprojection error (the median over cameras) exceeds
    ``FLAG_ERROR`` of the image height: the cameras agree with each other, so none is flagged, but the bodies fit
    the keypoints loosely everywhere (low resolution, keypoint noise, or a calibration off in the same way in
    every camera). None when the capture is within it."""
    finite = {n: e for n, e in errors.items() if np.isfinite(e)}
    if not finite or float(np.median(list(finite.values()))) <= FLAG_ERROR:
        return None
    low, high = min(finite.values()), max(finite.values())
    return (
        f"every camera's median reprojection is {100 * low:.2f}-{100 * high:.2f} % of the image height (above "
        f"{100 * FLAG_ERROR:.1f} %): the cameras agree, so none is flagged, but the bodies fit the keypoints loosely "
        "(low resolution, keypoint noise, or a calibration off alike in every camera)"
    )


def flag_cameras(
    names: list[str],
    errors: dict[str, float],
    ious: dict[str, float],
    disagreed: dict[str, float],
    corrections: dict[str, tuple[float, float]] | None = None,
) -> dict[str, str]:
    """Cameras that disagree with the others, with the reason (module constants; ``disagreed``: the fraction of
    frames where the camera's person did not match the others' beyond the view threshold; ``corrections``: how far
    the body fit moved each camera, degrees and cm)."""
    flags = {}
    for name in names:
        turn, shift = (corrections or {}).get(name, (0.0, 0.0))
        if turn > FLAG_TURN or shift > FLAG_SHIFT:
            flags[name] = (
                f"the body fit had to turn this camera by {turn:.1f} degrees and move it by {shift:.1f} cm to match "
                "the others: check its calibration (--keep-calibration keeps it as given)"
            )
            continue
        if disagreed.get(name, 0.0) > FLAG_DISAGREED:
            flags[name] = (
                f"its detection disagrees with the other cameras in {100 * disagreed[name]:.0f} % of the frames: "
                "another person in view, or this camera's calibration or synchronisation is off"
            )
            continue
        others = [errors[n] for n in names if n != name and np.isfinite(errors[n])]
        typical = float(np.median(others)) if others else np.nan
        error = errors[name]
        if not np.isfinite(error):
            flags[name] = "the body was never reprojected into this camera (no usable view)"
        elif error > _flag_threshold(typical):
            flags[name] = (
                f"median reprojection {100 * error:.2f} % of the image height against {100 * typical:.2f} % for the "
                "other cameras: check this camera's calibration and synchronisation"
            )
        elif ious.get(name, 1.0) < FLAG_IOU:
            flags[name] = f"body-vs-mask IoU {ious[name]:.2f}: the mask or the calibration is off"
    return flags
