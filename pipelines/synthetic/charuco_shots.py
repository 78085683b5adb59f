"""ChArUco calibration shots of the synthetic rig (``calib/`` of a synthetic capture).

Shot 0 is the reference: the board lies flat on the floor with its frame equal to the world frame (origin at
the board's chessboard origin, z down into the floor, the ZJU convention). The other shots hold the board
upright-ish at random places in the capture volume, facing random directions, so that each camera sees it in
several shots and neighbouring cameras share shots. Optional per-camera close-ups (the intrinsics shots of a
studio protocol) hold the board 0.6-1.2 m in front of one camera. Each pixel integrates 3x3 sub-pixel rays.
Written files:

* ``calib/<camera>/<shot:03d>.jpg`` for every camera and shot (also where the board is not visible);
* ``calib/<camera>/intrinsics/<k:03d>.jpg``: that camera's close-ups, when asked for;
* ``calib/board.json``: the board definition and the reference shot;
* ``calib/ground_truth.npz``: ``world_from_board`` (S, 4, 4) of every shot (generator truth, for tests) and,
  with close-ups, ``close_world_from_board`` (C, K, 4, 4).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from fitting.files import write_image
from pipelines.calibration.board import BoardSpec
from pipelines.datasets.camera import Camera
from pipelines.synthetic.scene import pixel_directions, studio_background

_MARGIN = 0.04  # white panel border around the printed board, metres
_TEXTURE_PPM = 1000  # texture pixels per metre
_SUPERSAMPLE = 3  # sub-pixel rays per pixel side


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` about the unit ``axis`` (Rodrigues)."""
    return cv2.Rodrigues(np.asarray(axis, dtype=np.float64) * angle)[0]


def board_poses(spec: BoardSpec, n_shots: int, seed: int) -> np.ndarray:
    """(S, 4, 4) ``world_from_board``: shot 0 on the floor (identity), the rest random and facing outwards."""
    rng = np.random.default_rng(seed + 7)
    width, height = spec.size
    poses = [np.eye(4)]
    for _ in range(1, n_shots):
        radius, angle = 1.6 * np.sqrt(rng.uniform(0.0, 1.0)), rng.uniform(0, 2 * np.pi)
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
        centre = np.array([radius * np.sin(angle), -radius * np.cos(angle), rng.uniform(-2.0, -0.3)])
        pose = np.eye(4)
        pose[:3, :3] = rotation
        pose[:3, 3] = centre - rotation @ np.array([width / 2, height / 2, 0.0])
        poses.append(pose)
    return np.stack(poses)


def close_up_poses(spec: BoardSpec, camera: Camera, n_shots: int, seed: int) -> np.ndarray:
    """(S, 4, 4) ``world_from_board`` of one camera's close-up shots: the board held 0.6-1.2 m in front of the
    lens, its centre anywhere in the image (partly outside the frame is fine), strongly tilted. These are the
    per-camera intrinsics shots of a studio protocol; they pin the principal point and distortion."""
    rng = np.random.default_rng([seed + 11, int.from_bytes(camera.name.encode(), "little") % 2**32])
    width, height = spec.size
    world_from_cam = np.linalg.inv(camera.cam_from_world)
    poses = []
    for _ in range(n_shots):
        pixel = rng.uniform(0.15, 0.85, size=2) * [camera.width, camera.height]
        ray = np.linalg.solve(camera.K, [*pixel, 1.0])
        depth = rng.uniform(0.6, 1.2)
        # board facing the camera (z away from it), then tilted about its own x and y axes
        z_axis = ray / np.linalg.norm(ray)
        x_axis = np.cross([0.0, 1.0, 0.0], z_axis)
        x_axis /= np.linalg.norm(x_axis)
        base = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], axis=1)
        tilt = _axis_rotation([1.0, 0, 0], rng.uniform(-0.8, 0.8)) @ _axis_rotation([0, 1.0, 0], rng.uniform(-0.8, 0.8))
        cam_from_board = np.eye(4)
        cam_from_board[:3, :3] = base @ tilt @ _axis_rotation([0, 0, 1.0], rng.uniform(-0.4, 0.4))
        cam_from_board[:3, 3] = ray * depth - cam_from_board[:3, :3] @ np.array([width / 2, height / 2, 0.0])
        poses.append(world_from_cam @ cam_from_board)
    return np.stack(poses)


def _board_hits(centre: np.ndarray, dirs: np.ndarray, world_from_board: np.ndarray, spec: BoardSpec):
    """Ray-board intersection of (..., 3) rays from ``centre``: (inside mask, board coordinates (..., 3), depth t)."""
    rotation, origin = world_from_board[:3, :3], world_from_board[:3, 3]
    normal = rotation[:, 2]
    denom = dirs @ normal
    t = ((origin - centre) @ normal) / np.where(np.abs(denom) < 1e-9, 1e-9, denom)
    local = (centre + t[..., None] * dirs - origin) @ rotation
    width, height = spec.size
    inside = (t > 0) & (local[..., 0] > -_MARGIN) & (local[..., 0] < width + _MARGIN)
    inside &= (local[..., 1] > -_MARGIN) & (local[..., 1] < height + _MARGIN)
    return inside, local, t


def _render_board(
    camera: Camera,
    dirs: np.ndarray,
    background: np.ndarray,
    texture: np.ndarray,
    world_from_board: np.ndarray,
    spec: BoardSpec,
    supersample: int = _SUPERSAMPLE,
) -> np.ndarray:
    """(H, W, 3) shot: the board over ``background``, each pixel the mean of ``supersample``^2 sub-pixel rays
    (a sensor integrates over the pixel area; point-sampled edges would jitter the corners by ~0.1 px)."""
    centre, normal = camera.centre, world_from_board[:3, 2]
    image = background.copy()
    if (centre - world_from_board[:3, 3]) @ normal >= 0:  # the camera is behind the board's printed side
        return image
    inside, local, t = _board_hits(centre, dirs, world_from_board, spec)
    if not inside.any():
        return image
    rows, cols = np.nonzero(inside)
    y0, y1 = max(rows.min() - 2, 0), min(rows.max() + 3, camera.height)
    x0, x1 = max(cols.min() - 2, 0), min(cols.max() + 3, camera.width)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    sub_x = (np.arange(x0, x1)[:, None] + offsets).ravel().astype(np.float32)
    sub_y = (np.arange(y0, y1)[:, None] + offsets).ravel().astype(np.float32)
    map_x, map_y = np.meshgrid(sub_x, sub_y)
    # board coordinates are a smooth function of the pixel (undistortion, then a homography): bilinear
    # interpolation between pixel centres is exact to ~1e-6 of a pixel; rays that miss the plane stay far away
    coords = np.where((t > 0)[..., None], local[..., :2], 1e3).astype(np.float32)
    sub_local = cv2.remap(coords, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    width, height = spec.size
    sub_inside = (sub_local[..., 0] > -_MARGIN) & (sub_local[..., 0] < width + _MARGIN)
    sub_inside &= (sub_local[..., 1] > -_MARGIN) & (sub_local[..., 1] < height + _MARGIN)
    distance = np.median(t[inside])
    ppm = float(min(_TEXTURE_PPM, 2.0 * supersample * camera.K[0, 0] / distance))  # texture matched to the footprint
    scaled = cv2.resize(texture, None, fx=ppm / _TEXTURE_PPM, fy=ppm / _TEXTURE_PPM, interpolation=cv2.INTER_AREA)
    tex_x = (sub_local[..., 0] + _MARGIN) * ppm - 0.5
    tex_y = (sub_local[..., 1] + _MARGIN) * ppm - 0.5
    sampled = cv2.remap(scaled, tex_x, tex_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    shading = 0.55 + 0.35 * abs(float(normal @ np.array([0.3, -0.4, -0.85])))
    # each pixel's mean over its supersample^2 sub-pixels: INTER_AREA at a whole factor is the block mean
    size = (x1 - x0, y1 - y0)
    coverage = cv2.resize(sub_inside.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    board = cv2.resize(np.where(sub_inside, sampled, 0).astype(np.float32), size, interpolation=cv2.INTER_AREA)
    image[y0:y1, x0:x1] = image[y0:y1, x0:x1] * (1 - coverage[..., None]) + (board * shading / 255.0)[..., None]
    return image


def write_calibration_shots(
    folder: Path,
    cameras: list[Camera],
    n_shots: int,
    seed: int,
    spec: BoardSpec = BoardSpec(),
    progress: bool = True,
    close_ups: int = 0,
) -> None:
    """Render ``n_shots`` board poses into every camera, plus ``close_ups`` per-camera close-up shots under
    ``<camera>/intrinsics/``, and write the ``calib/`` folder (module docstring)."""
    folder = Path(folder)
    width, height = spec.size
    board_px = spec.board().generateImage((round(width * _TEXTURE_PPM), round(height * _TEXTURE_PPM)), marginSize=0)
    pad = round(_MARGIN * _TEXTURE_PPM)
    texture = cv2.copyMakeBorder(board_px, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    poses = board_poses(spec, n_shots, seed)
    close = np.stack([close_up_poses(spec, camera, close_ups, seed) for camera in cameras]) if close_ups else None
    for c, camera in enumerate(tqdm(cameras, desc="calibration shots", unit="camera", disable=not progress)):
        dirs = pixel_directions(camera).astype(np.float64)
        background = studio_background(camera, dirs)
        shots = [(folder / camera.name / f"{shot:03d}.jpg", pose) for shot, pose in enumerate(poses)]
        if close is not None:
            shots += [(folder / camera.name / "intrinsics" / f"{k:03d}.jpg", pose) for k, pose in enumerate(close[c])]
        for path, pose in shots:
            path.parent.mkdir(parents=True, exist_ok=True)
            image = _render_board(camera, dirs, background, texture, pose, spec)
            bgr = cv2.cvtColor((image * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR)
            write_image(path, bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    (folder / "board.json").write_text(
        json.dumps({**asdict(spec), "reference_shot": 0, "cameras": [c.name for c in cameras]}, indent=2)
    )
    extra = {} if close is None else {"close_world_from_board": close}
    np.savez(folder / "ground_truth.npz", world_from_board=poses, **extra)
