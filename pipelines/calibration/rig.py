"""Calibration, part 2: rig extrinsics from shared ChArUco shots and one joint bundle adjustment.

Initialisation walks a graph over cameras and board shots from the reference shot, whose board frame is the
world frame (ZJU convention: board on the floor, z = x cross y points down into the floor, metres): a camera
that sees a placed board gets ``cam_from_world = cam_from_board (world_from_board)^-1`` (PnP), a board seen by a
placed camera gets ``world_from_board = (cam_from_world)^-1 cam_from_board``; a board need not be seen by all
cameras at once.

The bundle adjustment refines, jointly, every camera's pose and intrinsics (fx, fy, cx, cy, k1, k2, p1, p2, k3;
any of ``FIXABLE`` held at their initial value, k3 = 0 by default) and every non-reference board pose,
minimising the Huber-robust reprojection error of all detected corners (``pipelines/calibration/sparse_lm.py``: sparse
Levenberg-Marquardt). Design choice: the board is kept an exact rigid body (6 parameters per shot) instead of
free 3-D points as in a structure-from-motion bundle adjustment (pycolmap), and partial ChArUco views need no
fixed point set per frame (as ``cv2.calibrateMultiview`` expects).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse
from scipy.spatial.transform import Rotation

from pipelines.calibration.charuco import CalibrationError, Detection, Intrinsics
from pipelines.calibration.sparse_lm import solve_sparse_lm

N_CAM_PARAMS, N_BOARD_PARAMS = 15, 6  # camera: rvec, t, fx, fy, cx, cy, k1, k2, p1, p2, k3; board: rvec, t
FIXABLE = {"k3": [14], "tangential": [12, 13], "principal_point": [8, 9]}  # indices into the camera parameters


@dataclass
class RigSolution:
    """Solved rig: per camera K (3, 3), dist (5,), cam_from_world (4, 4); per shot world_from_board (4, 4);
    reprojection RMS overall and per camera (px) and mean error, over the corners kept; corners rejected as
    outliers."""

    K: dict[str, np.ndarray]
    dist: dict[str, np.ndarray]
    cam_from_world: dict[str, np.ndarray]
    world_from_board: dict[str, np.ndarray]
    rms: float
    camera_rms: dict[str, float]
    mean_error: float
    rejected: int = 0


def _pose(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0]
    out[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return out


def initial_extrinsics(
    intrinsics: dict[str, Intrinsics], detections: dict[str, list[Detection]], reference: str
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
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
        raise CalibrationError(
            f"camera(s) {', '.join(missing)} share no board shot with the rest of the rig "
            f"(connected to the reference shot '{reference}')"
        )
    return cam_from_world, world_from_board


def _project(points_world: np.ndarray, cam: np.ndarray) -> np.ndarray:
    """OpenCV projection (k1, k2, p1, p2, k3) of (N, 3) points with per-point camera params (N, 15)."""
    rotation = Rotation.from_rotvec(cam[:, 0:3])
    x = rotation.apply(points_world) + cam[:, 3:6]
    xn, yn = x[:, 0] / x[:, 2], x[:, 1] / x[:, 2]
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = cam[:, 6:15].T
    r2 = xn * xn + yn * yn
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)


@dataclass
class _Observations:
    """Corner observations: camera index (N,), board index (N,; -1 = the reference board), board points (N, 3),
    pixels (N, 2)."""

    cam: np.ndarray
    board: np.ndarray
    points: np.ndarray
    pixels: np.ndarray

    def subset(self, keep: np.ndarray) -> _Observations:
        return _Observations(self.cam[keep], self.board[keep], self.points[keep], self.pixels[keep])


def _observations(detections, cams, boards, world_from_board) -> _Observations:
    cam_index, board_index = {c: i for i, c in enumerate(cams)}, {b: i for i, b in enumerate(boards)}
    obs_cam, obs_board, points, pixels = [], [], [], []
    for cam in cams:
        for det in detections[cam]:
            if det.shot not in world_from_board:
                continue
            obs_cam += [cam_index[cam]] * len(det.ids)
            obs_board += [board_index.get(det.shot, -1)] * len(det.ids)
            points.append(det.object_points)
            pixels.append(det.image_points)
    return _Observations(
        np.array(obs_cam),
        np.array(obs_board),
        np.concatenate(points).astype(np.float64),
        np.concatenate(pixels).astype(np.float64),
    )


def _residuals(x: np.ndarray, obs: _Observations, n_cam_params: int) -> np.ndarray:
    """(2N,) reprojection residuals (px) of all observations for the parameter vector ``x``."""
    cam_params = x[:n_cam_params].reshape(-1, N_CAM_PARAMS)
    board_params = np.concatenate([np.zeros((1, 6)), x[n_cam_params:].reshape(-1, N_BOARD_PARAMS)])
    b = board_params[obs.board + 1]  # index 0 = the reference board (identity)
    world = Rotation.from_rotvec(b[:, :3]).apply(obs.points) + b[:, 3:]
    return (_project(world, cam_params[obs.cam]) - obs.pixels).ravel()


def _refine(x0: np.ndarray, obs: _Observations, n_cam_params: int, free: np.ndarray) -> np.ndarray:
    """One robust (Huber, 1 px) sparse Levenberg-Marquardt solve from ``x0`` over the ``free`` parameters."""
    rows = np.arange(len(obs.cam))
    pattern_rows, pattern_cols = [], []
    for k in range(N_CAM_PARAMS):
        for r in (0, 1):
            pattern_rows.append(2 * rows + r)
            pattern_cols.append(obs.cam * N_CAM_PARAMS + k)
    has_board = obs.board >= 0
    for k in range(N_BOARD_PARAMS):
        for r in (0, 1):
            pattern_rows.append(2 * rows[has_board] + r)
            pattern_cols.append(n_cam_params + obs.board[has_board] * N_BOARD_PARAMS + k)
    pattern_rows, pattern_cols = np.concatenate(pattern_rows), np.concatenate(pattern_cols)
    sparsity = scipy.sparse.csc_matrix(
        (np.ones(len(pattern_rows), dtype=bool), (pattern_rows, pattern_cols)), shape=(2 * len(obs.cam), len(x0))
    )

    def residuals(z: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[free] = z
        return _residuals(x, obs, n_cam_params)

    x = x0.copy()
    x[free] = solve_sparse_lm(residuals, x0[free], sparsity[:, free], huber=1.0).x
    return x


def bundle_adjust(
    intrinsics: dict[str, Intrinsics],
    detections: dict[str, list[Detection]],
    reference: str,
    cam_from_world: dict[str, np.ndarray],
    world_from_board: dict[str, np.ndarray],
    outlier_px: float = 1.0,
    fixed: frozenset[str] = frozenset({"k3"}),
) -> RigSolution:
    """Joint refinement of all cameras (pose + intrinsics but the ``fixed`` groups of ``FIXABLE``) and
    non-reference board poses.

    Two passes: after the first, corners whose reprojection error exceeds max(``outlier_px``, 5 x the median)
    are dropped (mislocalised corners of strongly foreshortened boards) and the solve is repeated;
    ``RigSolution.rejected`` counts them.
    """
    unknown = set(fixed) - set(FIXABLE)
    if unknown:
        raise CalibrationError(f"cannot fix {sorted(unknown)}: fixable are {sorted(FIXABLE)}")
    cams = sorted(cam_from_world)
    boards = sorted(b for b in world_from_board if b != reference)
    obs = _observations(detections, cams, boards, world_from_board)
    x = []
    for cam in cams:
        K, dist = intrinsics[cam].K, intrinsics[cam].dist
        x += [
            *cv2.Rodrigues(cam_from_world[cam][:3, :3])[0].ravel(),
            *cam_from_world[cam][:3, 3],
            K[0, 0],
            K[1, 1],
            K[0, 2],
            K[1, 2],
            *dist[:5],
        ]
    for board in boards:
        x += [*cv2.Rodrigues(world_from_board[board][:3, :3])[0].ravel(), *world_from_board[board][:3, 3]]
    n_cam_params = len(cams) * N_CAM_PARAMS
    free = np.ones(len(x), dtype=bool)
    for group in fixed:
        for index in FIXABLE[group]:
            free[index:n_cam_params:N_CAM_PARAMS] = False
    x = _refine(np.array(x), obs, n_cam_params, free)
    errors = np.linalg.norm(_residuals(x, obs, n_cam_params).reshape(-1, 2), axis=1)
    keep = errors <= max(outlier_px, 5.0 * float(np.median(errors)))
    if not keep.all():
        obs = obs.subset(keep)
        x = _refine(x, obs, n_cam_params, free)
    return _solution(x, _residuals(x, obs, n_cam_params), cams, boards, reference, obs.cam, int((~keep).sum()))


def _solution(x, fun, cams, boards, reference, obs_cam, rejected) -> RigSolution:
    errors = np.linalg.norm(fun.reshape(-1, 2), axis=1)
    K, dist, cam_from_world = {}, {}, {}
    for i, cam in enumerate(cams):
        p = x[i * N_CAM_PARAMS : (i + 1) * N_CAM_PARAMS]
        cam_from_world[cam] = _pose(p[0:3], p[3:6])
        K[cam] = np.array([[p[6], 0, p[8]], [0, p[7], p[9]], [0, 0, 1.0]])
        dist[cam] = p[10:15].copy()
    world_from_board = {reference: np.eye(4)}
    offset = len(cams) * N_CAM_PARAMS
    for j, board in enumerate(boards):
        p = x[offset + j * N_BOARD_PARAMS : offset + (j + 1) * N_BOARD_PARAMS]
        world_from_board[board] = _pose(p[:3], p[3:])
    camera_rms = {cam: float(np.sqrt(np.mean(errors[obs_cam == i] ** 2))) for i, cam in enumerate(cams)}
    return RigSolution(
        K,
        dist,
        cam_from_world,
        world_from_board,
        float(np.sqrt(np.mean(errors**2))),
        camera_rms,
        float(np.mean(errors)),
        rejected,
    )
