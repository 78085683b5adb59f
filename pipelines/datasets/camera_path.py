"""Camera paths saved by ``narf-view`` and rendered by ``narf-render-video --camera-path`` (docs/formats.md §11).

A JSON object::

    {"format": "narf-camera-path", "version": 1, "width": 512, "height": 384,
     "keyframes": [{"cam_from_world": [[...4 rows...]], "fov_y_degrees": 50.0, "frame": 12}, ...]}

``cam_from_world`` is an OpenCV extrinsic (x right, y down, z forward; metres, the capture's world); ``fov_y_degrees``
the vertical field of view of a centred pinhole of ``width`` x ``height`` pixels; ``frame`` the capture frame shown
(its SMPL parameters). Between keyframes the camera centre and field of view move linearly, the rotation by
spherical interpolation, and the frame is rounded from a linear ramp (:func:`interpolate`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

FORMAT = "narf-camera-path"


@dataclass
class Keyframe:
    cam_from_world: np.ndarray
    fov_y_degrees: float
    frame: int


@dataclass
class CameraPath:
    width: int
    height: int
    keyframes: list[Keyframe]

    def to_json(self) -> dict:
        keys = [
            {"cam_from_world": k.cam_from_world.tolist(), "fov_y_degrees": k.fov_y_degrees, "frame": k.frame}
            for k in self.keyframes
        ]
        return {"format": FORMAT, "version": 1, "width": self.width, "height": self.height, "keyframes": keys}


def intrinsics(width: int, height: int, fov_y_degrees: float) -> np.ndarray:
    """(3, 3) K of a centred pinhole: f = (H / 2) / tan(fov_y / 2), principal point at the image centre (pixel
    centres at integers)."""
    focal = 0.5 * height / np.tan(np.radians(fov_y_degrees) / 2)
    return np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])


def _fail(path: Path, what: str) -> ValueError:
    return ValueError(f"{path}: {what} (a camera path saved by narf-view: docs/formats.md §11)")


def read_camera_path(path: Path) -> CameraPath:
    """Read and check a camera path: sizes 16..8192, at least one keyframe, rigid finite extrinsics (a rotation of
    determinant 1, bottom row 0 0 0 1), field of view in (1, 170) degrees, frames non-negative integers (not
    booleans)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise _fail(path, f"not readable JSON ({err})") from err
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise _fail(path, f'not a camera path ("format" must be "{FORMAT}")')
    size = [data.get("width"), data.get("height")]
    if not all(isinstance(v, int) and 16 <= v <= 8192 for v in size):
        raise _fail(path, f"width and height must be integers in 16..8192, got {size}")
    keys = data.get("keyframes")
    if not isinstance(keys, list) or not keys:
        raise _fail(path, "no keyframes")
    out = []
    for k, key in enumerate(keys):
        try:
            matrix = np.asarray(key["cam_from_world"], dtype=np.float64)
            fov, frame = float(key["fov_y_degrees"]), key["frame"]
        except (KeyError, TypeError, ValueError) as err:
            raise _fail(path, f"keyframe {k} needs cam_from_world (4x4), fov_y_degrees and frame ({err})") from err
        rigid = matrix.shape == (4, 4) and np.isfinite(matrix).all()
        if not rigid or not np.allclose(matrix[:3, :3] @ matrix[:3, :3].T, np.eye(3), atol=1e-4):
            raise _fail(path, f"keyframe {k}: cam_from_world is not a finite rigid 4x4 transform")
        if np.linalg.det(matrix[:3, :3]) < 0:
            raise _fail(path, f"keyframe {k}: cam_from_world mirrors the world (its rotation's determinant is -1)")
        if not np.array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0]):
            raise _fail(path, f"keyframe {k}: cam_from_world's bottom row must be 0 0 0 1, got {matrix[3].tolist()}")
        if not 1 < fov < 170 or isinstance(frame, bool) or not isinstance(frame, int) or frame < 0:
            raise _fail(path, f"keyframe {k}: fov_y_degrees must be in (1, 170) and frame an integer >= 0")
        out.append(Keyframe(matrix, fov, frame))
    return CameraPath(size[0], size[1], out)


def interpolate(path: CameraPath, n_frames: int) -> list[Keyframe]:
    """``n_frames`` cameras evenly along the keyframes (first and last included; one keyframe: held)."""
    keys = path.keyframes
    if len(keys) == 1:
        return [keys[0]] * n_frames
    s = np.linspace(0, len(keys) - 1, n_frames)
    knots = np.arange(len(keys))
    world_from_cam = Rotation.from_matrix(np.stack([k.cam_from_world[:3, :3].T for k in keys]))
    rotations = Slerp(knots, world_from_cam)(s).as_matrix()
    centres = np.stack([-k.cam_from_world[:3, :3].T @ k.cam_from_world[:3, 3] for k in keys])
    out = []
    for i, t in enumerate(s):
        centre = np.stack([np.interp(t, knots, centres[:, d]) for d in range(3)])
        matrix = np.eye(4)
        matrix[:3, :3] = rotations[i].T
        matrix[:3, 3] = -rotations[i].T @ centre
        fov = float(np.interp(t, knots, [k.fov_y_degrees for k in keys]))
        out.append(Keyframe(matrix, fov, int(round(np.interp(t, knots, [k.frame for k in keys])))))
    return out
