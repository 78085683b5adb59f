"""Calibration, part 2: rig extrinsics from shared ChArUco shots and one joint bundle adjustment.

Initialisation walks a graph over cameras and board shots from the reference shot, whose board frame is the
world frame (ZJU convention: board on the floor, z = x cross y points down into the floor, metres): a camera
that sees a placed board gets ``cam_from_world = cam_from_board (world_from_board)^-1`` (PnP), a board seen by a
placed camera gets ``world_from_board = (cam_from_world)^-1 cam_from_board``; a board need not be seen by all
cameras at once.

The bundle adjustment refines, jointly, every camera's pose and intrinsics (fx, fy, cx, cy, k1, k2, p1, p2; k3
fixed) and every non-reference board pose, minimising the reprojection error of all detected corners
(``scipy.optimize.least_squares``, trust region with a sparse Jacobian). Design choice: the board is kept an
exact rigid body (6 parameters per shot) instead of free 3-D points as in a structure-from-motion bundle
adjustment (pycolmap), and partial ChArUco views need no fixed point set per frame (as
``cv2.calibrateMultiview`` expects).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from pipelines.calibration import CalibrationError, Detection, Intrinsics

N_CAM_PARAMS, N_BOARD_PARAMS = 14, 6


@dataclass
class RigSolution:
    """Solved rig: per camera K (3, 3), dist (5,), cam_from_world (4, 4); per shot world_from_board (4, 4);
    reprojection RMS overall and per camera (px)."""

    K: dict[str, np.ndarray]
    dist: dict[str, np.ndarray]
    cam_from_world: dict[str, np.ndarray]
    world_from_board: dict[str, np.ndarray]
    rms: float
    camera_rms: dict[str, float]
    mean_error: float


def _pose(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0]
    out[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return out


def initial_extrinsics(intrinsics: dict[str, Intrinsics], detections: dict[str, list[Detection]],
                       reference: str) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:  # fmt: skip
    """Breadth-first placement of cameras and boards from the reference shot (module docstring)."""
    cam_from_board: dict[tuple[str, str], np.ndarray] = {}
    corners: dict[tuple[str, str], int] = {}
    for cam, dets in detections.items():
        K, dist = intrinsics[cam].K, intrinsics[cam].dist
        for det in dets:
            # IPPE: the planar-target solver, free of the mirror ambiguity that iterative PnP can fall into
            ok, rvec, tvec = cv2.solvePnP(det.object_points, det.image_points, K, dist, flags=cv2.SOLVEPNP_IPPE)
            if not ok:
                continue
            projected = cv2.projectPoints(det.object_points, rvec, tvec, K, dist)[0].reshape(-1, 2)
            if np.sqrt(np.mean(np.sum((projected - det.image_points) ** 2, axis=1))) > 1.5:
                continue  # an unreliable single-view pose: leave this link out of the initialisation
            cam_from_board[(cam, det.shot)] = _pose(rvec, tvec)
            corners[(cam, det.shot)] = len(det.ids)
    # strongest links first: each camera and board is placed from its best-observed neighbour
    cam_from_board = dict(sorted(cam_from_board.items(), key=lambda item: -corners[item[0]]))
    if not any(shot == reference for _, shot in cam_from_board):
        raise CalibrationError(f"no camera sees the board in the reference shot '{reference}'")
    world_from_board = {reference: np.eye(4)}
    cam_from_world: dict[str, np.ndarray] = {}
    queue = deque([("board", reference)])
    while queue:
        kind, name = queue.popleft()
        for (cam, shot), transform in cam_from_board.items():
            if kind == "board" and shot == name and cam not in cam_from_world:
                cam_from_world[cam] = transform @ np.linalg.inv(world_from_board[shot])
                queue.append(("camera", cam))
            elif kind == "camera" and cam == name and shot not in world_from_board:
                world_from_board[shot] = np.linalg.inv(cam_from_world[cam]) @ transform
                queue.append(("board", shot))
    missing = sorted(set(detections) - set(cam_from_world))
    if missing:
        raise CalibrationError(f"camera(s) {', '.join(missing)} share no board shot with the rest of the rig "
                               f"(connected to the reference shot '{reference}')")  # fmt: skip
    return cam_from_world, world_from_board


def _project(points_world: np.ndarray, cam: np.ndarray) -> np.ndarray:
    """OpenCV projection (k1, k2, p1, p2, k3 = 0) of (N, 3) points with per-point camera params (N, 14)."""
    rotation = Rotation.from_rotvec(cam[:, 0:3])
    x = rotation.apply(points_world) + cam[:, 3:6]
    xn, yn = x[:, 0] / x[:, 2], x[:, 1] / x[:, 2]
    fx, fy, cx, cy, k1, k2, p1, p2 = cam[:, 6:14].T
    r2 = xn * xn + yn * yn
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)


def bundle_adjust(
    intrinsics: dict[str, Intrinsics], detections: dict[str, list[Detection]], reference: str,
    cam_from_world: dict[str, np.ndarray], world_from_board: dict[str, np.ndarray],
) -> RigSolution:
    """Joint refinement of all cameras (pose + intrinsics) and non-reference board poses."""
    cams = sorted(cam_from_world)
    boards = sorted(b for b in world_from_board if b != reference)
    cam_index, board_index = {c: i for i, c in enumerate(cams)}, {b: i for i, b in enumerate(boards)}
    obs_cam, obs_board, obs_points, obs_pixels = [], [], [], []
    for cam in cams:
        for det in detections[cam]:
            if det.shot not in world_from_board:
                continue
            obs_cam += [cam_index[cam]] * len(det.ids)
            obs_board += [board_index.get(det.shot, -1)] * len(det.ids)
            obs_points.append(det.object_points)
            obs_pixels.append(det.image_points)
    obs_cam, obs_board = np.array(obs_cam), np.array(obs_board)
    obs_points = np.concatenate(obs_points).astype(np.float64)
    obs_pixels = np.concatenate(obs_pixels).astype(np.float64)
    x0 = []
    for cam in cams:
        K, dist = intrinsics[cam].K, intrinsics[cam].dist
        x0 += [*cv2.Rodrigues(cam_from_world[cam][:3, :3])[0].ravel(), *cam_from_world[cam][:3, 3],
               K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist[:4]]  # fmt: skip
    for board in boards:
        x0 += [*cv2.Rodrigues(world_from_board[board][:3, :3])[0].ravel(), *world_from_board[board][:3, 3]]
    n_cam_params = len(cams) * N_CAM_PARAMS

    def residuals(x: np.ndarray) -> np.ndarray:
        cam_params = x[:n_cam_params].reshape(-1, N_CAM_PARAMS)
        board_params = np.concatenate([np.zeros((1, 6)), x[n_cam_params:].reshape(-1, N_BOARD_PARAMS)])
        b = board_params[obs_board + 1]  # index 0 = the reference board (identity)
        world = Rotation.from_rotvec(b[:, :3]).apply(obs_points) + b[:, 3:]
        return (_project(world, cam_params[obs_cam]) - obs_pixels).ravel()

    sparsity = scipy.sparse.lil_matrix((2 * len(obs_cam), len(x0)), dtype=np.uint8)
    rows = np.arange(len(obs_cam))
    for k in range(N_CAM_PARAMS):
        for r in (0, 1):
            sparsity[2 * rows + r, obs_cam * N_CAM_PARAMS + k] = 1
    has_board = obs_board >= 0
    for k in range(N_BOARD_PARAMS):
        for r in (0, 1):
            sparsity[2 * rows[has_board] + r, n_cam_params + obs_board[has_board] * N_BOARD_PARAMS + k] = 1
    result = least_squares(residuals, np.array(x0), jac_sparsity=sparsity, x_scale="jac", method="trf",
                           loss="soft_l1", f_scale=2.0, max_nfev=200)  # fmt: skip
    return _solution(result.x, result.fun, cams, boards, reference, obs_cam)


def _solution(x, fun, cams, boards, reference, obs_cam) -> RigSolution:
    errors = np.linalg.norm(fun.reshape(-1, 2), axis=1)
    K, dist, cam_from_world = {}, {}, {}
    for i, cam in enumerate(cams):
        p = x[i * N_CAM_PARAMS : (i + 1) * N_CAM_PARAMS]
        cam_from_world[cam] = _pose(p[0:3], p[3:6])
        K[cam] = np.array([[p[6], 0, p[8]], [0, p[7], p[9]], [0, 0, 1.0]])
        dist[cam] = np.array([p[10], p[11], p[12], p[13], 0.0])
    world_from_board = {reference: np.eye(4)}
    offset = len(cams) * N_CAM_PARAMS
    for j, board in enumerate(boards):
        p = x[offset + j * N_BOARD_PARAMS : offset + (j + 1) * N_BOARD_PARAMS]
        world_from_board[board] = _pose(p[:3], p[3:])
    camera_rms = {cam: float(np.sqrt(np.mean(errors[obs_cam == i] ** 2))) for i, cam in enumerate(cams)}
    return RigSolution(K, dist, cam_from_world, world_from_board, float(np.sqrt(np.mean(errors**2))), camera_rms,
                       float(np.mean(errors)))  # fmt: skip
