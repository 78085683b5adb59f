"""ChArUco calibration shots of the synthetic rig (``calib/`` of a synthetic capture).

Shot 0 is the reference: the board lies flat on the floor with its frame equal to the world frame (origin at
the board's chessboard origin, z down into the floor, the ZJU convention). The other shots hold the board
upright-ish at random places in the capture volume, facing random directions, so that each camera sees it in
several shots and neighbouring cameras share shots. Written files:

* ``calib/<camera>/<shot:03d>.jpg`` for every camera and shot (also where the board is not visible);
* ``calib/board.json``: the board definition and the reference shot;
* ``calib/ground_truth.npz``: ``world_from_board`` (S, 4, 4) of every shot (generator truth, for tests).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from pipelines.synthetic_scene import studio_background
from pipelines.zju_mocap import Camera


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: squares along x / y, square and marker side (metres), ArUco dictionary name."""

    squares_x: int = 8
    squares_y: int = 6
    square_length: float = 0.12
    marker_length: float = 0.09
    dictionary: str = "DICT_5X5_100"

    def board(self) -> cv2.aruco.CharucoBoard:
        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary '{self.dictionary}'")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_length, self.marker_length,
                                      dictionary)  # fmt: skip

    @property
    def size(self) -> tuple[float, float]:
        return self.squares_x * self.square_length, self.squares_y * self.square_length


_MARGIN = 0.04  # white panel border around the printed board, metres
_TEXTURE_PPM = 1000  # texture pixels per metre


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` about the unit ``axis`` (Rodrigues)."""
    return cv2.Rodrigues(np.asarray(axis, dtype=np.float64) * angle)[0]


def board_poses(spec: BoardSpec, n_shots: int, seed: int) -> np.ndarray:
    """(S, 4, 4) ``world_from_board``: shot 0 on the floor (identity), the rest random and facing outwards."""
    rng = np.random.default_rng(seed + 7)
    width, height = spec.size
    poses = [np.eye(4)]
    for _ in range(1, n_shots):
        yaw = rng.uniform(0, 2 * np.pi)
        elevation = rng.uniform(-0.2, 0.5)  # facing slightly up towards the cameras
        facing = np.array([np.sin(yaw) * np.cos(elevation), -np.cos(yaw) * np.cos(elevation), -np.sin(elevation)])
        z_axis = -facing
        y_axis = np.array([0.0, 0.0, 1.0]) - z_axis * z_axis[2]
        y_axis /= np.linalg.norm(y_axis)
        x_axis = np.cross(y_axis, z_axis)
        roll = rng.uniform(-0.5, 0.5)
        x_axis, y_axis = np.cos(roll) * x_axis + np.sin(roll) * y_axis, -np.sin(roll) * x_axis + np.cos(roll) * y_axis
        # strong tilts about the board's own axes give the perspective that separates focal length and distance
        tilt = _axis_rotation(x_axis, rng.uniform(-0.7, 0.7)) @ _axis_rotation(y_axis, rng.uniform(-0.7, 0.7))
        rotation = tilt @ np.stack([x_axis, y_axis, z_axis], axis=1)
        radius, angle = rng.uniform(0.0, 1.6), rng.uniform(0, 2 * np.pi)
        centre = np.array([radius * np.cos(angle), radius * np.sin(angle), rng.uniform(-1.7, -0.4)])
        pose = np.eye(4)
        pose[:3, :3] = rotation
        pose[:3, 3] = centre - rotation @ np.array([width / 2, height / 2, 0.0])
        poses.append(pose)
    return np.stack(poses)


def _render_board(camera: Camera, dirs: np.ndarray, background: np.ndarray, texture: np.ndarray,
                  world_from_board: np.ndarray, spec: BoardSpec) -> np.ndarray:  # fmt: skip
    rotation, origin = world_from_board[:3, :3], world_from_board[:3, 3]
    centre = camera.centre
    normal = rotation[:, 2]
    image = background.copy()
    if (centre - origin) @ normal >= 0:  # the camera is behind the board's printed side
        return image
    denom = dirs @ normal
    t = ((origin - centre) @ normal) / np.where(np.abs(denom) < 1e-9, 1e-9, denom)
    local = (centre + t[..., None] * dirs - origin) @ rotation  # board coordinates
    width, height = spec.size
    inside = (t > 0) & (local[..., 0] > -_MARGIN) & (local[..., 0] < width + _MARGIN)
    inside &= (local[..., 1] > -_MARGIN) & (local[..., 1] < height + _MARGIN)
    if not inside.any():
        return image
    distance = np.median(t[inside])
    ppm = min(_TEXTURE_PPM, 2.0 * camera.K[0, 0] / distance)  # texture resolution matched to the footprint
    scaled = cv2.resize(texture, None, fx=ppm / _TEXTURE_PPM, fy=ppm / _TEXTURE_PPM, interpolation=cv2.INTER_AREA)
    map_x = ((local[..., 0] + _MARGIN) * ppm - 0.5).astype(np.float32)
    map_y = ((local[..., 1] + _MARGIN) * ppm - 0.5).astype(np.float32)
    sampled = cv2.remap(scaled, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    shading = 0.55 + 0.35 * abs(float(normal @ np.array([0.3, -0.4, -0.85])))
    image[inside] = (sampled[inside] / 255.0 * shading)[:, None]
    return image


def write_calibration_shots(folder: Path, cameras: list[Camera], n_shots: int, seed: int,
                            spec: BoardSpec = BoardSpec(), progress: bool = True) -> None:  # fmt: skip
    """Render ``n_shots`` board poses into every camera and write the ``calib/`` folder (module docstring)."""
    from pipelines.synthetic import pixel_directions

    folder = Path(folder)
    width, height = spec.size
    board_px = spec.board().generateImage((round(width * _TEXTURE_PPM), round(height * _TEXTURE_PPM)), marginSize=0)
    pad = round(_MARGIN * _TEXTURE_PPM)
    texture = cv2.copyMakeBorder(board_px, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    poses = board_poses(spec, n_shots, seed)
    for camera in tqdm(cameras, desc="calibration shots", unit="camera", disable=not progress):
        dirs = pixel_directions(camera).astype(np.float64)
        background = studio_background(camera, dirs)
        (folder / camera.name).mkdir(parents=True, exist_ok=True)
        for shot, pose in enumerate(poses):
            image = _render_board(camera, dirs, background, texture, pose, spec)
            bgr = cv2.cvtColor((image * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR)
            cv2.imwrite(str(folder / camera.name / f"{shot:03d}.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    (folder / "board.json").write_text(json.dumps({**asdict(spec), "reference_shot": 0,
                                                   "cameras": [c.name for c in cameras]}, indent=2))  # fmt: skip
    np.savez(folder / "ground_truth.npz", world_from_board=poses)
