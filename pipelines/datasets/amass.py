"""AMASS motions (``docs/formats.md`` §7): one ``.npz`` per sequence, SMPL+H (or SMPL-X) parameters in a z-up world.

Read with ``np.load(allow_pickle=False)``: the arrays AMASS stores are plain numbers and strings, so no pickle is
ever needed (a file that needs one is refused rather than unpickled).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipelines.datasets.errors import CaptureError

#: SMPL's first 22 joints (pelvis ... wrists) are the body joints of SMPL+H and SMPL-X in the same order; SMPL's
#: joints 22/23 (hands) stay at rest.
BODY_JOINTS = 22
#: Pose widths: SMPL+H (52 joints) and SMPL-X (55 joints: + jaw and eyes before the hands).
POSE_WIDTHS = (156, 165)


@dataclass(frozen=True)
class AmassMotion:
    """An AMASS sequence.

    Attributes:
        path: the ``.npz`` file.
        poses: (T, 72) SMPL axis-angle (root orientation about the pelvis, 21 body joints, hands at rest).
        trans: (T, 3) smplx ``transl`` in metres (z-up world).
        betas: (B,) shape of the captured person (SMPL+H: 16).
        gender: 'male', 'female', 'neutral' or '' when the file has none.
        fps: the capture rate (``mocap_framerate``; SMPL-X files: ``mocap_frame_rate``).
    """

    path: Path
    poses: np.ndarray
    trans: np.ndarray
    betas: np.ndarray
    gender: str
    fps: float


def _array(data, key: str, path: Path) -> np.ndarray:
    try:
        return np.asarray(data[key])
    except ValueError as err:  # object arrays need a pickle: refused
        raise CaptureError(f"{path}: '{key}' is stored as a Python object (pickle), which is not read") from err


def _numbers(data, key: str, path: Path) -> np.ndarray:
    """``data[key]`` as float64, or an error naming the file and the key."""
    try:
        return _array(data, key, path).astype(np.float64)
    except (TypeError, ValueError) as err:
        raise CaptureError(f"{path}: '{key}' is not numeric ({err})") from None


def read_amass(path: str | Path) -> AmassMotion:
    """Read an AMASS ``.npz`` (``poses`` (T, 156 or 165), ``trans`` (T, 3), ``betas``, ``gender``, frame rate).

    Raises:
        CaptureError: not an npz, a missing key, wrong shapes or non-finite values.
    """
    path = Path(path)
    try:
        with open(path, "rb") as file:
            magic = file.read(6)
    except OSError as err:
        raise CaptureError(f"{path}: not a readable AMASS .npz ({err})") from err
    if not magic.startswith((b"PK\x03\x04", b"\x93NUMPY")):  # zip (npz) or npy; numpy would call anything else pickled
        raise CaptureError(
            f"{path}: not an .npz archive (an AMASS motion is a zip of arrays); it starts with {magic!r}"
        )
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise CaptureError(f"{path}: not a readable AMASS .npz ({err})") from err
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise CaptureError(f"{path}: a single .npy array, not an AMASS .npz archive")
    with data:
        rate_key = next((k for k in ("mocap_framerate", "mocap_frame_rate") if k in data.files), None)
        missing = [k for k in ("poses", "trans") if k not in data.files] + ([] if rate_key else ["mocap_framerate"])
        if missing:
            raise CaptureError(f"{path}: missing keys {missing} (has {sorted(data.files)}); not an AMASS motion")
        poses, trans = _numbers(data, "poses", path), _numbers(data, "trans", path)
        betas = _numbers(data, "betas", path).reshape(-1) if "betas" in data.files else np.zeros(16)
        gender = str(_array(data, "gender", path)) if "gender" in data.files else ""
        rate = _numbers(data, rate_key, path)
    if rate.size != 1:
        raise CaptureError(f"{path}: '{rate_key}' has shape {rate.shape}, expected one number (frames per second)")
    fps = float(rate.reshape(()))
    if poses.ndim != 2 or poses.shape[1] not in POSE_WIDTHS or poses.shape[0] == 0:
        raise CaptureError(f"{path}: 'poses' has shape {poses.shape}, expected (T, 156) SMPL+H or (T, 165) SMPL-X")
    if trans.shape != (poses.shape[0], 3):
        raise CaptureError(f"{path}: 'trans' has shape {trans.shape}, expected ({poses.shape[0]}, 3)")
    if not (np.isfinite(poses).all() and np.isfinite(trans).all()) or not (np.isfinite(fps) and fps > 0):
        raise CaptureError(f"{path}: NaN or infinite values, or a frame rate that is not positive ({fps})")
    smpl = np.zeros((poses.shape[0], 72))
    smpl[:, : 3 * BODY_JOINTS] = poses[:, : 3 * BODY_JOINTS]
    return AmassMotion(path, smpl, trans, betas, gender.strip("b'"), fps)


def write_amass(path: str | Path, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray, gender: str, fps: float):
    """Write an AMASS-layout SMPL+H ``.npz`` (poses (T, 156), trans, betas (16,), gender, mocap_framerate, dmpls)."""
    poses = np.asarray(poses, np.float64)
    if poses.shape[1] == 72:
        full = np.zeros((poses.shape[0], 156))
        full[:, : 3 * BODY_JOINTS] = poses[:, : 3 * BODY_JOINTS]
        poses = full
    np.savez(
        path,
        poses=poses,
        trans=np.asarray(trans, np.float64),
        betas=np.pad(np.asarray(betas, np.float64).reshape(-1), (0, 16))[:16],
        gender=np.array(gender),
        mocap_framerate=np.array(float(fps)),
        dmpls=np.zeros((poses.shape[0], 8)),
    )
