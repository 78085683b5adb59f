"""Camera calibration from ChArUco shots, part 1: detection and per-camera intrinsics (issue: narf-calibrate).

Detection uses the OpenCV >= 4.7 API (``CharucoDetector.detectBoard``, ``board.matchImagePoints``) with
sub-pixel corners. Intrinsics: pinhole + (k1, k2, p1, p2, k3) by ``cv2.calibrateCamera`` on every view with
enough corners; views whose RMS exceeds max(``outlier_factor`` x the median, 1 px) are dropped and the solve
repeated. On the synthetic rig this stage alone reaches ~0.16 px RMS but only 1-2 % focal accuracy (7-14
mostly fronto-parallel views per camera); the 0.5 % target needs the joint bundle adjustment over all cameras
and board poses. Extrinsics (graph initialisation and joint bundle adjustment) are not implemented yet.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pipelines.synthetic_calib import BoardSpec

MIN_CORNERS = 6


class CalibrationError(ValueError):
    """Calibration input is unusable (the message names the camera or file)."""


@dataclass
class Detection:
    """ChArUco corners of one image: ids (N,), image points (N, 2), board points (N, 3) in metres."""

    shot: str
    ids: np.ndarray
    image_points: np.ndarray
    object_points: np.ndarray


@dataclass
class Intrinsics:
    """Result of one camera: K (3, 3), dist (5,), RMS and per-view RMS (px), the views used and dropped."""

    camera: str
    K: np.ndarray
    dist: np.ndarray
    rms: float
    image_size: tuple[int, int]
    view_rms: dict[str, float] = field(default_factory=dict)
    rejected: list[str] = field(default_factory=list)


def detect_charuco(image: np.ndarray, board: cv2.aruco.CharucoBoard, shot: str = "") -> Detection | None:
    """ChArUco corners of a grayscale or BGR image, refined to sub-pixel; None when fewer than 6 are found."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    params = cv2.aruco.CharucoParameters()
    detector = cv2.aruco.CharucoDetector(board, params)
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < MIN_CORNERS:
        return None
    corners = corners.reshape(-1, 1, 2).astype(np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    corners = cv2.cornerSubPix(gray, corners, (2, 2), (-1, -1), criteria)  # 5x5 window (half-size 2)
    object_points, image_points = board.matchImagePoints(corners, ids)
    return Detection(shot, ids.reshape(-1), image_points.reshape(-1, 2), object_points.reshape(-1, 3))


def detect_folder(folder: Path, spec: BoardSpec) -> tuple[list[Detection], tuple[int, int], dict[str, str]]:
    """Detect the board in every image of one camera folder.

    Returns:
        detections, image size (width, height), and a report {shot: "ok N corners" | reason}.

    Raises:
        CalibrationError: unreadable images or mixed image sizes in the folder.
    """
    board = spec.board()
    detections, report, size = [], {}, None
    images = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    if not images:
        raise CalibrationError(f"{folder}: no images")
    for path in images:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise CalibrationError(f"{path}: unreadable image")
        if size is None:
            size = (image.shape[1], image.shape[0])
        elif (image.shape[1], image.shape[0]) != size:
            raise CalibrationError(f"{path}: image is {image.shape[1]}x{image.shape[0]}, other images of "
                                   f"{Path(folder).name} are {size[0]}x{size[1]}")  # fmt: skip
        if cv2.Laplacian(image, cv2.CV_64F).var() < 5.0:
            report[path.stem] = "blank or blurred"
            continue
        found = detect_charuco(image, board, path.stem)
        if found is None:
            report[path.stem] = "board not found"
        else:
            detections.append(found)
            report[path.stem] = f"ok {len(found.ids)} corners"
    return detections, size, report


def calibrate_intrinsics(
    camera: str, detections: list[Detection], image_size: tuple[int, int], fix_k3: bool = True,
    outlier_factor: float = 3.0, min_views: int = 3,
) -> Intrinsics:
    """Per-camera pinhole + distortion with outlier-view rejection.

    Raises:
        CalibrationError: the camera sees the board in fewer than ``min_views`` usable views.
    """
    views = [d for d in detections if len(d.ids) >= MIN_CORNERS]
    if len(views) < min_views:
        raise CalibrationError(f"camera {camera}: the board is detected in {len(views)} shot(s), at least "
                               f"{min_views} are needed for its intrinsics")  # fmt: skip
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    rejected: list[str] = []
    while True:
        result = _solve(views, image_size, flags)
        per_view = result["view_rms"]
        median = float(np.median(list(per_view.values())))
        worst = max(per_view, key=per_view.get)
        if per_view[worst] <= max(outlier_factor * median, 1.0) or len(views) <= min_views:
            break
        rejected.append(worst)
        views = [v for v in views if v.shot != worst]
    return Intrinsics(camera, result["K"], result["dist"], result["rms"], image_size, per_view, rejected)


def _solve(views: list[Detection], image_size: tuple[int, int], flags: int) -> dict:
    object_points = [v.object_points.astype(np.float32) for v in views]
    image_points = [v.image_points.astype(np.float32) for v in views]
    width, height = image_size
    guess = np.array([[1.2 * max(width, height), 0, width / 2], [0, 1.2 * max(width, height), height / 2],
                      [0, 0, 1]])  # fmt: skip
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(object_points, image_points, image_size, guess, None,
                                                     flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS)  # fmt: skip
    view_rms = {}
    for view, obj, img, rvec, tvec in zip(views, object_points, image_points, rvecs, tvecs):
        projected = cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
        view_rms[view.shot] = float(np.sqrt(np.mean(np.sum((projected - img) ** 2, axis=1))))
    return {"K": K, "dist": dist.reshape(-1)[:5], "rms": float(rms), "view_rms": view_rms}
