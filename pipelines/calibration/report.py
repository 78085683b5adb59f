"""PNG report of a calibration: the rig seen from above and per-camera reprojection errors (OpenCV drawing)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from skimage.transform import SimilarityTransform

from fitting.files import atomic_output, write_image
from pipelines.datasets.camera import Camera

_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _save(path: Path, canvas: np.ndarray) -> None:
    with atomic_output(path) as tmp:
        write_image(tmp, canvas)


def draw_rig(
    path: Path,
    cameras: list[Camera],
    world_from_board: dict[str, np.ndarray],
    board_size: tuple[float, float],
    size: int = 800,
) -> None:
    """Top view (world x right, y down the image; z is vertical): camera centres with viewing directions and
    frusta, and the outline of every board pose (the reference board in red)."""
    centres = np.array([c.centre for c in cameras])
    width, height = board_size
    outline = np.array([[0, 0, 0], [width, 0, 0], [width, height, 0], [0, height, 0]], dtype=float)
    boards = {name: outline @ pose[:3, :3].T + pose[:3, 3] for name, pose in world_from_board.items()}
    points = np.concatenate([centres[:, :2], *(b[:, :2] for b in boards.values())])
    low, high = points.min(0) - 0.3, points.max(0) + 0.3
    scale = (size - 80) / max(high - low)
    to_px = lambda xy: np.round((np.asarray(xy) - low) * scale + 40).astype(np.int32)  # noqa: E731
    canvas = np.full((size, size, 3), 255, np.uint8)
    for name, corners in boards.items():
        colour = (40, 40, 220) if np.allclose(world_from_board[name], np.eye(4)) else (160, 160, 160)
        cv2.polylines(canvas, [to_px(corners[:, :2])], True, colour, 1, cv2.LINE_AA)
    for camera in cameras:
        forward = camera.cam_from_world[2, :3]
        right = camera.cam_from_world[0, :3]
        left, right_pt = (camera.centre + 0.35 * forward + s * 0.15 * right for s in (-1, 1))
        cv2.polylines(
            canvas, [to_px(np.array([camera.centre, left, right_pt])[:, :2])], True, (200, 90, 20), 2, cv2.LINE_AA
        )
        (text_w, _), _ = cv2.getTextSize(camera.name, _FONT, 0.35, 1)
        x, y = to_px(camera.centre[:2] - 0.25 * forward[:2])
        anchor = (int(np.clip(x - text_w // 2, 2, size - text_w - 2)), int(np.clip(y, 12, size - 4)))
        cv2.putText(canvas, camera.name, anchor, _FONT, 0.35, (0, 0, 0), 1, cv2.LINE_AA)  # label centred, kept inside
    cv2.putText(
        canvas,
        "rig from above (world x, y; z vertical); red: reference board",
        (10, 20),
        _FONT,
        0.5,
        (0, 0, 0),
        1,
        cv2.LINE_AA,
    )
    _save(path, canvas)


def draw_residuals(path: Path, camera_rms: dict[str, float], width: int = 800, height: int = 360) -> None:
    """Bar chart of the reprojection RMS (px) of every camera after the bundle adjustment."""
    canvas = np.full((height, width, 3), 255, np.uint8)
    names = list(camera_rms)
    top = max(max(camera_rms.values()), 0.5)
    bar = (width - 60) / max(len(names), 1)
    for k, name in enumerate(names):
        value = camera_rms[name]
        x0, x1 = int(40 + k * bar + 2), int(40 + (k + 1) * bar - 2)
        y = int(height - 50 - value / top * (height - 100))
        cv2.rectangle(canvas, (x0, y), (x1, height - 50), (200, 90, 20), -1)
        cv2.putText(canvas, f"{value:.2f}", (x0, y - 4), _FONT, 0.3, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(canvas, name[-3:], (x0, height - 35), _FONT, 0.3, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(canvas, "reprojection RMS per camera (px)", (10, 20), _FONT, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    _save(path, canvas)


def _rotation_deg(rotation: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(rotation).magnitude()))


def compare_cameras(previous: list[Camera], solved: list[Camera]) -> dict:
    """Per-camera differences between two calibrations of the same rig (same order): camera centre (mm),
    rotation (deg), focal length (%), as they stand and after the similarity transform that best maps the solved
    camera centres onto the previous ones (scikit-image's Umeyama estimate; the two may use different world
    frames)."""
    old = np.array([c.centre for c in previous])
    new = np.array([c.centre for c in solved])
    similarity = SimilarityTransform.from_estimate(new, old)
    if not similarity:
        raise ValueError(f"cannot align the solved cameras with the previous ones: {similarity}")
    scale = float(np.cbrt(np.linalg.det(similarity.params[:3, :3])))
    old_from_new = similarity.params[:3, :3] / scale
    aligned = similarity(new)
    cameras = {}
    for k, (a, b) in enumerate(zip(previous, solved)):
        rot_a, rot_b = a.cam_from_world[:3, :3], b.cam_from_world[:3, :3]
        cameras[b.name] = {
            "centre_mm": float(np.linalg.norm(new[k] - old[k]) * 1000),
            "rotation_deg": _rotation_deg(rot_b @ rot_a.T),
            "focal_pct": float(abs(b.K[0, 0] / a.K[0, 0] - 1) * 100),
            "aligned_centre_mm": float(np.linalg.norm(aligned[k] - old[k]) * 1000),
            "aligned_rotation_deg": _rotation_deg(rot_b @ old_from_new.T @ rot_a.T),
        }
    worst = {key: max(v[key] for v in cameras.values()) for key in next(iter(cameras.values()))}
    return {"max": worst, "alignment_scale": scale, "cameras": cameras}
