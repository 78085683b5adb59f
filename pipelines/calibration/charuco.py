"""Camera calibration from ChArUco shots, part 1: detection and per-camera intrinsics.

Detection uses the OpenCV >= 4.7 API (``CharucoDetector.detectBoard``, ``board.matchImagePoints``) with
sub-pixel corners. Intrinsics: pinhole + (k1, k2, p1, p2, k3; groups fixable) by ``cv2.calibrateCamera`` on
every view with enough corners; views whose RMS exceeds max(``outlier_factor`` x the median, 1 px) are dropped
and the solve repeated. These per-camera values initialise the joint bundle adjustment over all cameras and
board poses (``pipelines/calibration/rig.py``), which is what reaches the accuracy targets.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pipelines.calibration.board import BoardSpec
from pipelines.datasets.images import read_image

MIN_CORNERS = 6
_FIX_FLAGS = {
    "k3": cv2.CALIB_FIX_K3,
    "tangential": cv2.CALIB_ZERO_TANGENT_DIST,
    "principal_point": cv2.CALIB_FIX_PRINCIPAL_POINT,
}


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


def detect_charuco(
    image: np.ndarray, board: cv2.aruco.CharucoBoard, shot: str = "", upscale: int | None = None
) -> Detection | None:
    """ChArUco corners of a grayscale or BGR image, refined to sub-pixel; None when fewer than 6 are found.

    The board is searched in the image enlarged ``upscale`` times (default: 2 for images whose longer side is
    under 1500 px, else 1): on small or strongly foreshortened boards a marker cell spans only 1-2 pixels, too
    few for the ArUco bit reader. The corners are the detector's own sub-pixel refinement (``cornerSubPix`` with
    a window per corner that stops short of the nearest marker corner); a fixed window, as a second pass,
    doubles the error of foreshortened corners, whose marker corners lie within a pixel or two.
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if upscale is None:
        upscale = 2 if max(gray.shape) < 1500 else 1
    params = cv2.aruco.DetectorParameters()
    params.perspectiveRemovePixelPerCell = 8
    detector = cv2.aruco.CharucoDetector(board, cv2.aruco.CharucoParameters(), params)
    search = cv2.resize(gray, None, fx=upscale, fy=upscale, interpolation=cv2.INTER_CUBIC) if upscale > 1 else gray
    corners, ids, _, _ = detector.detectBoard(search)
    if ids is None or len(ids) < MIN_CORNERS:
        return None
    corners = ((corners.reshape(-1, 1, 2) + 0.5) / upscale - 0.5).astype(np.float32)  # pixel-centre convention
    object_points, image_points = board.matchImagePoints(corners, ids)
    return Detection(shot, ids.reshape(-1), image_points.reshape(-1, 2), object_points.reshape(-1, 3))


def _shot_images(folder: Path) -> list[tuple[str, Path]]:
    """(shot name, path) of a camera folder: shared shots ``*.jpg`` (the file name links the views of one board
    pose across cameras) and the camera's own close-ups ``intrinsics/*.jpg`` (named ``<camera>/intrinsics/<stem>``,
    so they never link to another camera)."""
    suffixes = (".jpg", ".jpeg", ".png")
    shots = [(p.stem, p) for p in sorted(folder.iterdir()) if p.suffix.lower() in suffixes]
    if (folder / "intrinsics").is_dir():
        shots += [
            (f"{folder.name}/intrinsics/{p.stem}", p)
            for p in sorted((folder / "intrinsics").iterdir())
            if p.suffix.lower() in suffixes
        ]
    return shots


def detect_folder(folder: Path, spec: BoardSpec) -> tuple[list[Detection], tuple[int, int], dict[str, str]]:
    """Detect the board in every image of one camera folder (shared shots and ``intrinsics/`` close-ups).

    Returns:
        detections, image size (width, height), and a report {shot: "ok N corners" | reason}.

    Raises:
        CalibrationError: unreadable images or mixed image sizes in the folder.
    """
    board = spec.board()
    folder = Path(folder)
    detections, report, size = [], {}, None
    images = _shot_images(folder)
    if not images:
        raise CalibrationError(f"{folder}: no images")
    for shot, path in images:
        image = read_image(path, cv2.IMREAD_GRAYSCALE)
        if size is None:
            size = (image.shape[1], image.shape[0])
        elif (image.shape[1], image.shape[0]) != size:
            raise CalibrationError(
                f"{path}: image is {image.shape[1]}x{image.shape[0]}, other images of "
                f"{folder.name} are {size[0]}x{size[1]}"
            )
        if cv2.Laplacian(image, cv2.CV_64F).var() < 5.0:
            report[shot] = "blank or blurred"
            continue
        found = detect_charuco(image, board, shot)
        if found is None:
            report[shot] = "board not found"
        else:
            detections.append(found)
            report[shot] = f"ok {len(found.ids)} corners"
    return detections, size, report


def calibrate_intrinsics(
    camera: str,
    detections: list[Detection],
    image_size: tuple[int, int],
    fixed: frozenset[str] = frozenset({"k3"}),
    outlier_factor: float = 3.0,
    min_views: int = 3,
) -> Intrinsics:
    """Per-camera pinhole + distortion with outlier-view rejection; ``fixed`` names parameter groups held at
    their initial value: ``k3`` (0), ``tangential`` (p1 = p2 = 0), ``principal_point`` (the image centre).

    Raises:
        CalibrationError: the camera sees the board in fewer than ``min_views`` usable views.
    """
    views = [d for d in detections if len(d.ids) >= MIN_CORNERS]
    if len(views) < min_views:
        raise CalibrationError(
            f"camera {camera}: the board is detected in {len(views)} shot(s), at least "
            f"{min_views} are needed for its intrinsics"
        )
    flags = 0
    for group in fixed:
        flags |= _FIX_FLAGS[group]
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
    # the image centre in OpenCV's pixel-centre convention is ((w - 1) / 2, (h - 1) / 2)
    guess = np.array(
        [[1.2 * max(width, height), 0, (width - 1) / 2], [0, 1.2 * max(width, height), (height - 1) / 2], [0, 0, 1]]
    )
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        object_points, image_points, image_size, guess, None, flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS
    )
    view_rms = {}
    for view, obj, img, rvec, tvec in zip(views, object_points, image_points, rvecs, tvecs):
        projected = cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
        view_rms[view.shot] = float(np.sqrt(np.mean(np.sum((projected - img) ** 2, axis=1))))
    return {"K": K, "dist": dist.reshape(-1)[:5], "rms": float(rms), "view_rms": view_rms}
