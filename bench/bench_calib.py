"""Calibration runtime and accuracy on the synthetic 21-camera ring (shot rendering untimed): 30 shared ChArUco
shots alone, and with 20 close-ups per camera (the synthetic capture's default), at 512^2 and 1024^2."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from pipelines.calibration.board import BoardSpec
from pipelines.calibration.charuco import calibrate_intrinsics, detect_folder
from pipelines.calibration.rig import bundle_adjust, initial_extrinsics
from pipelines.synthetic.charuco_shots import write_calibration_shots
from pipelines.synthetic.scene import ring_cameras

SETTINGS = ((512, 0), (512, 20), (1024, 0), (1024, 20))  # (resolution, close-ups per camera)


def _errors(cameras, solution) -> tuple[float, float, float]:
    focal, centre, rotation = [], [], []
    for camera in cameras:
        estimate = solution.cam_from_world[camera.name]
        focal.append(abs(solution.K[camera.name][0, 0] / camera.K[0, 0] - 1) * 100)
        centre.append(np.linalg.norm(-estimate[:3, :3].T @ estimate[:3, 3] - camera.centre) * 1000)
        delta = estimate[:3, :3] @ camera.cam_from_world[:3, :3].T
        rotation.append(np.degrees(np.arccos(np.clip((np.trace(delta) - 1) / 2, -1, 1))))
    return max(focal), max(centre), max(rotation)


def run() -> list[dict]:
    rows = []
    for resolution, close_ups in SETTINGS:
        cameras = ring_cameras(21, resolution, seed=0)
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            write_calibration_shots(folder, cameras, 30, seed=0, progress=False, close_ups=close_ups)
            start = time.perf_counter()
            detections, intrinsics = {}, {}
            for camera in cameras:
                found, size, _ = detect_folder(folder / camera.name, BoardSpec())
                detections[camera.name] = found
                intrinsics[camera.name] = calibrate_intrinsics(camera.name, found, size)
            detect_seconds = time.perf_counter() - start
            cam_from_world, world_from_board = initial_extrinsics(intrinsics, detections, "000")
            solution = bundle_adjust(intrinsics, detections, "000", cam_from_world, world_from_board)
            seconds = time.perf_counter() - start
        focal, centre, rotation = _errors(cameras, solution)
        rows.append(
            {
                "benchmark": "calibration (detect + intrinsics + BA)",
                "setting": f"21 cams x 30 shots + {close_ups} close-ups, {resolution}^2",
                "value": f"{seconds:.0f} s ({detect_seconds:.0f} s detection); mean reproj "
                f"{solution.mean_error:.2f} px, max focal err {focal:.3f} %, max centre err {centre:.1f} mm, "
                f"max rot err {rotation:.3f} deg",
            }
        )
    return rows
