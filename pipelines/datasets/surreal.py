"""SURREAL clips (gulvarol/surreal), as its generator writes them (``docs/formats.md §5``).

A clip is ``<split>/run<k>/<seq>/<seq>_c%04d.mp4`` (320 x 240 RGB) beside ``_info.mat`` (annotations),
``_segm.mat`` and ``_depth.mat`` (per-frame keys ``segm_1 ...``, ``depth_1 ...``: **1-based**). The ``.mat`` files
are MATLAB 5 files read with ``scipy.io.loadmat``, which never runs code from the file.

The camera is SURREAL's fixed Blender camera: K from a 60 mm lens on a 32 mm sensor at 320 x 240, and extrinsics
from ``camLoc`` with R = diag(1, -1, -1) R_world2bcam. That R has determinant -1 (Blender's camera matrix), so
the renders are mirrored relative to a right-handed camera; it is returned as it is, because only then does
``round(K [R | t] joints3D)`` reproduce the stored ``joints2D``. ``right_handed_view`` gives the equivalent proper
rotation for a horizontally flipped image.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.io

from pipelines.datasets.errors import CaptureError

WIDTH, HEIGHT = 320, 240
#: Blender: 60 mm lens, 32 mm sensor width, 320 x 240 pixels -> f = 600 px, centre (160, 120).
SURREAL_K = np.array([[600.0, 0.0, 160.0], [0.0, 600.0, 120.0], [0.0, 0.0, 1.0]])
#: World -> Blender camera axes (the transposed first 3 columns of SURREAL's camera matrix_world).
_R_WORLD2BCAM = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]]).T
#: Blender camera (y up, looking along -z) -> computer-vision camera (y down, looking along +z).
_BCAM2CV = np.diag([1.0, -1.0, -1.0])
INFO_KEYS = ("pose", "shape", "zrot", "camLoc", "joints2D", "joints3D", "gender")


@dataclass(frozen=True)
class SurrealClip:
    """One clip's annotations, frame-major.

    Attributes:
        path: the ``_info.mat`` file.
        K: (3, 3) intrinsics. cam_from_world: (4, 4), rotation with det -1 (module docstring).
        pose: (T, 72) SMPL axis-angle. shape: (T, 10) betas. zrot: (T,) body rotation about z (radians).
        gender: (T,) 0 = female, 1 = male. joints2d: (T, 24, 2) pixels, 0-based. joints3d: (T, 24, 3) metres.
    """

    path: Path
    K: np.ndarray
    cam_from_world: np.ndarray
    pose: np.ndarray
    shape: np.ndarray
    zrot: np.ndarray
    gender: np.ndarray
    joints2d: np.ndarray
    joints3d: np.ndarray

    @property
    def n_frames(self) -> int:
        return self.pose.shape[0]


def surreal_cam_from_world(cam_loc: np.ndarray) -> np.ndarray:
    """SURREAL's extrinsics from the Blender camera location: [R | -R camLoc], R = diag(1,-1,-1) R_world2bcam.

    Args:
        cam_loc: (3,) camera location in SURREAL's world (metres).

    Returns:
        (4, 4) cam_from_world whose rotation has determinant -1.
    """
    rotation = _BCAM2CV @ _R_WORLD2BCAM
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = -rotation @ np.asarray(cam_loc, dtype=np.float64).reshape(3)
    return out


def right_handed_view(K: np.ndarray, cam_from_world: np.ndarray, width: int = WIDTH) -> tuple[np.ndarray, np.ndarray]:
    """The same view with a proper rotation, for the horizontally flipped image (u' = width - 1 - u).

    Row 0 of [R | t] is negated and c_x becomes width - 1 - c_x (pixel centres at integers), so that
    projecting with the result lands on ``width - 1 - u`` for every point projecting to ``u`` before.
    """
    proper = cam_from_world.copy()
    proper[0] *= -1
    flipped_K = K.copy()
    flipped_K[0, 2] = width - 1 - K[0, 2]
    return flipped_K, proper


def _per_frame(info: dict, key: str, path: Path, n_frames: int, dims: tuple[int, ...] = ()) -> np.ndarray:
    """loadmat's (dims..., T) array (a (T, 1) column for scalars) as (T, *reversed dims): joints2D (2, 24, T) ->
    (T, 24, 2)."""
    array = np.asarray(info[key])
    if not dims:
        array = array.reshape(-1)
        if array.shape != (n_frames,):
            raise CaptureError(f"{path}: '{key}' has {array.size} values, expected one per frame ({n_frames})")
        return array
    if array.ndim == len(dims) and n_frames == 1:  # MATLAB drops a trailing singleton frame axis
        array = array[..., None]
    if array.shape != (*dims, n_frames):
        expected = "x".join(str(d) for d in (*dims, n_frames))
        raise CaptureError(f"{path}: '{key}' has shape {array.shape}, expected {expected}")
    return np.ascontiguousarray(np.transpose(array, tuple(range(array.ndim))[::-1]))


def read_surreal_info(path: str | Path) -> SurrealClip:
    """Read a SURREAL ``_info.mat`` into frame-major arrays and the clip's camera (module docstring).

    Raises:
        CaptureError: the file is missing or unreadable, lacks a key, or has inconsistent shapes.
    """
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: no such SURREAL _info.mat file")
    try:
        info = scipy.io.loadmat(str(path))
    except (scipy.io.matlab.MatReadError, ValueError, TypeError, OSError, NotImplementedError) as err:
        raise CaptureError(f"{path}: not a readable MATLAB file ({err})") from err
    missing = [key for key in INFO_KEYS if key not in info]
    if missing:
        raise CaptureError(f"{path}: missing keys {missing} (a SURREAL _info.mat has {', '.join(INFO_KEYS)})")
    try:
        pose = np.asarray(info["pose"], dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise CaptureError(f"{path}: 'pose' is not numeric ({err})") from None
    if pose.ndim == 1 or pose.shape[0] != 72:
        raise CaptureError(f"{path}: 'pose' has shape {pose.shape}, expected 72xT")
    n = pose.shape[1]
    cam_loc = np.asarray(info["camLoc"], dtype=np.float64)
    if cam_loc.size != 3:
        raise CaptureError(f"{path}: 'camLoc' has shape {cam_loc.shape}, expected 3x1")
    clip = SurrealClip(
        path=path,
        K=SURREAL_K.copy(),
        cam_from_world=surreal_cam_from_world(cam_loc),
        pose=pose.T.copy(),
        shape=_per_frame(info, "shape", path, n, (10,)).astype(np.float64),
        zrot=_per_frame(info, "zrot", path, n).astype(np.float64),
        gender=_per_frame(info, "gender", path, n).astype(np.int64),
        joints2d=_per_frame(info, "joints2D", path, n, (2, 24)).astype(np.float64),
        joints3d=_per_frame(info, "joints3D", path, n, (3, 24)).astype(np.float64),
    )
    for field, key in (("pose", "pose"), ("shape", "shape"), ("zrot", "zrot"), ("joints3d", "joints3D")):
        if not np.isfinite(getattr(clip, field)).all():
            raise CaptureError(f"{path}: '{key}' contains NaN or infinite values")
    if not np.isfinite(clip.cam_from_world).all():
        raise CaptureError(f"{path}: 'camLoc' contains NaN or infinite values")
    return clip


def clip_paths(info_path: str | Path) -> dict[str, Path]:
    """The files of the clip an ``_info.mat`` belongs to: ``video``, ``info``, ``segm``, ``depth``."""
    info_path = Path(info_path)
    stem = info_path.name.removesuffix("_info.mat")
    folder = info_path.parent
    return {
        "video": folder / f"{stem}.mp4",
        "info": info_path,
        "segm": folder / f"{stem}_segm.mat",
        "depth": folder / f"{stem}_depth.mat",
    }


def video_frame_count(path: Path) -> int:
    """Number of frames of an mp4, decoded (container metadata is not trusted)."""
    import imageio_ffmpeg

    if not path.is_file():
        raise CaptureError(f"{path}: no such SURREAL video")
    try:
        frames, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
    except (RuntimeError, OSError) as err:
        raise CaptureError(f"{path}: not a readable video ({err})") from err
    return int(frames)


def check_clip(info_path: str | Path) -> SurrealClip:
    """Read a clip's annotations and check that its mp4 and ``.mat`` files agree on the frame count.

    Raises:
        CaptureError: a file is missing, or the video and the annotations disagree.
    """
    clip = read_surreal_info(info_path)
    paths = clip_paths(info_path)
    n_video = video_frame_count(paths["video"])
    if n_video != clip.n_frames:
        raise CaptureError(f"{paths['video']}: {n_video} frames, but {paths['info'].name} annotates {clip.n_frames}")
    for kind in ("segm", "depth"):
        if not paths[kind].is_file():
            raise CaptureError(f"{paths[kind]}: missing (every SURREAL clip has _{kind}.mat)")
    return clip


def read_frame_maps(info_path: str | Path, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """Segmentation (240, 320) uint8 (0 background, p + 1 = SMPL joint p) and depth (240, 320) float32 metres
    (background 1e10) of 0-based ``frame``; the ``.mat`` keys are 1-based (``segm_1`` is frame 0)."""
    paths = clip_paths(info_path)
    maps = []
    for kind in ("segm", "depth"):
        key = f"{kind}_{frame + 1}"
        try:
            content = scipy.io.loadmat(str(paths[kind]), variable_names=[key])
        except (scipy.io.matlab.MatReadError, ValueError, TypeError, OSError, NotImplementedError) as err:
            raise CaptureError(f"{paths[kind]}: not a readable MATLAB file ({err})") from err
        if key not in content:
            raise CaptureError(f"{paths[kind]}: no '{key}' (frame {frame}; keys are 1-based)")
        value = np.asarray(content[key])
        if value.shape != (HEIGHT, WIDTH):
            raise CaptureError(f"{paths[kind]}: '{key}' has shape {value.shape}, expected {HEIGHT}x{WIDTH}")
        maps.append(value)
    return maps[0].astype(np.uint8), maps[1].astype(np.float32)
