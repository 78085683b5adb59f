"""Per-camera intrinsics from checkerboard shots (Pose2Sim's ``calibration/intrinsics/int_<camera>_img/``, or
any folder of shots per camera): OpenCV's sector-based corner detector, then ``cv2.calibrateCamera`` with the same
distortion model as the ChArUco path (k1, k2, p1, p2; k3 fixed at 0 by default).
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from pipelines.calibration.charuco import CalibrationError
from pipelines.datasets.images import read_image
from pipelines.datasets.rig_files import natural_key

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")
#: fewest shots with the whole board found that a camera needs
MIN_SHOTS = 3


def board_points(corners: tuple[int, int], square: float) -> np.ndarray:
    """(N, 3) inner-corner positions on the board plane (z = 0), row by row, in metres."""
    cols, rows = corners
    grid = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), -1).reshape(-1, 2)
    return np.hstack([grid * square, np.zeros((len(grid), 1))]).astype(np.float32)


def detect_corners(gray: np.ndarray, corners: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int]] | None:
    """(N, 2) sub-pixel inner corners of a checkerboard of ``corners`` = (columns, rows) and the pattern as seen
    (either orientation), or None if the board is not found whole. OpenCV's sector-based detector with its accuracy
    option (about 0.1-0.3 px RMS on the Pose2Sim demo's shots); the exhaustive search (slower: about a minute for a
    1088 x 1920 shot on 2 cores) only for shots the normal search misses."""
    accurate = cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
    for flags in (accurate, accurate | cv2.CALIB_CB_EXHAUSTIVE):
        for pattern in (corners, corners[::-1]):
            found, points = cv2.findChessboardCornersSB(gray, pattern, flags=flags)
            if found:
                return points.reshape(-1, 2), pattern
    return None


def camera_name(folder: Path) -> str:
    """``int_cam01_img`` -> ``cam01`` (Pose2Sim's folder names); other names are kept."""
    return re.sub(r"^int_|_img$", "", folder.name)


def calibrate_folder(folder: Path, corners: tuple[int, int], square: float, fix_k3: bool = True) -> dict:
    """Intrinsics of one camera from its shots: K, dist (5,), image size, RMS (px) and the shots used / rejected."""
    shots = sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=lambda p: natural_key(p.name)
    )
    object_points, image_points, used, rejected, size = [], [], [], [], None
    for shot in shots:
        gray = read_image(shot, cv2.IMREAD_GRAYSCALE)
        if size is not None and (gray.shape[1], gray.shape[0]) != size:
            raise CalibrationError(f"{shot}: {gray.shape[1]}x{gray.shape[0]}, the other shots are {size[0]}x{size[1]}")
        size = (gray.shape[1], gray.shape[0])
        found = detect_corners(gray, corners)
        if found is None:
            rejected.append(shot.name)
            continue
        points, pattern = found
        object_points.append(board_points(pattern, square))
        image_points.append(points.astype(np.float32))
        used.append(shot.name)
    if len(used) < MIN_SHOTS:
        raise CalibrationError(
            f"{folder}: the {corners[0]}x{corners[1]} checkerboard (inner corners) is found whole in {len(used)} of "
            f"{len(shots)} shots; at least {MIN_SHOTS} are needed"
        )
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    solve = lambda keep: cv2.calibrateCamera(  # noqa: E731
        [object_points[i] for i in keep], [image_points[i] for i in keep], size, None, None, flags=flags
    )
    keep = list(range(len(used)))
    rms, K, dist, _, _ = solve(keep)
    # a mis-detected board spoils the whole solution, so the worst shot is found by leaving each out in turn;
    # it goes while the RMS is over 1 px, leaving it out halves the RMS, and enough shots remain
    while rms > 1.0 and len(keep) > MIN_SHOTS:
        trials = [(solve([k for k in keep if k != out])[0], out) for out in keep]
        best_rms, out = min(trials)
        if best_rms > rms / 2:
            break
        rejected.append(f"{used[out]} (RMS {rms:.1f} px with it, {best_rms:.2f} px without)")
        keep.remove(out)
        rms, K, dist, _, _ = solve(keep)
    used = [used[k] for k in keep]
    return {
        "K": K,
        "dist": dist.reshape(-1)[:5],
        "size": size,
        "rms_px": float(rms),
        "used": used,
        "rejected": rejected,
    }


def shot_folders(root: Path) -> list[Path]:
    """The camera folders under ``root`` (those holding images), in natural order."""
    folders = sorted((p for p in root.iterdir() if p.is_dir()), key=lambda p: natural_key(p.name))
    folders = [f for f in folders if any(p.suffix.lower() in IMAGE_SUFFIXES for p in f.iterdir())]
    if not folders:
        raise CalibrationError(f"{root}: no camera folders with checkerboard shots")
    return folders


def calibrate_checkerboard_shots(root: Path, corners: tuple[int, int], square: float) -> dict[str, dict]:
    """Every camera folder under ``root`` (:func:`shot_folders`), by camera name."""
    return {camera_name(f): calibrate_folder(f, corners, square) for f in shot_folders(root)}
