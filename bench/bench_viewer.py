"""narf-view: preview frames per second while the camera moves, the still frame, and the first image after the page
opens.

A 2-minute CPU-preset fit of the default capture (``narf-fit --max-minutes 2``, fitted fresh under the benchmark's
cache) is viewed. The preview rate is what one tab's render thread does for each camera move: the pose's inputs, the
field rendered at the preview size (long side 128 / 192 / 256, 4:3) and the training sample counts, the picture and
depth made and both encoded as viser sends them (OpenCV: JPEG quality 90, depth as 24-bit fixed point in a PNG), over
24 cameras of an orbit. The still frame renders 512 x 384 at the evaluation sample counts. The first image is timed
in headless chromium (software WebGL) from the page request to the first preview sent to that tab, when chromium is
installed.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from pipelines.datasets.smpl_files import cache_dir, command_environment
from pipelines.viewer.avatar import camera_from_viewer, viewer_from_camera, z_depth

SIDES = (128, 192, 256)
ORBIT = 24


def _fit(run: Path) -> None:
    import shutil

    shutil.rmtree(run, ignore_errors=True)
    command = [sys.executable, "-c", "from pipelines.cli.fit import entrypoint; entrypoint()"]
    command += ["--subject", "taichi", "--out", str(run), "--max-minutes", "2", "--quiet"]
    subprocess.run(command, check=True, env=command_environment())


def _orbit(data, side: int) -> list:
    """ORBIT cameras turning about the up axis through the pelvis, starting at the first preset camera."""
    from scipy.spatial.transform import Rotation

    position, wxyz, fov = viewer_from_camera(data.cameras[0])
    centre = data.sources[0].make(0).world_from_joint()[0, :3, 3]
    cameras = []
    for angle in np.linspace(0, 2 * np.pi, ORBIT, endpoint=False):
        turn = Rotation.from_rotvec(angle * data.up)
        w, x, y, z = wxyz
        turned = (turn * Rotation.from_quat([x, y, z, w])).as_quat()
        eye = centre + turn.apply(position - centre)
        cameras.append(camera_from_viewer(eye, [turned[3], *turned[:3]], fov, 4 / 3, side))
    return cameras


def preview_rate(data, side: int, still: bool = False) -> float:
    """Frames per second of the preview path (module docstring) at long side ``side``; ``still``: at the evaluation
    sample counts, as the still frame renders (in one go here, not in bands)."""
    import cv2

    from fitting.evaluate import render_view
    from fitting.plots import to_numpy
    from pipelines.viewer.app import preview_config

    pose = data.sources[0].make(0)
    cameras = _orbit(data, side)
    config = data.config if still else preview_config(data.config)
    start = time.perf_counter()
    with torch.no_grad():
        for camera in cameras:
            render = to_numpy(render_view(data.field, camera, pose.pose_batch(), config))
            image = (np.clip(render["rgb"], 0, 1) * 255 + 0.5).astype(np.uint8)
            depth = z_depth(render["depth"], render["mask"], camera.K)
            cv2.imencode(".jpg", image[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])  # as viser encodes them
            packed = np.clip(depth * 100_000, 0, 2**24 - 1).astype(np.uint32).view(np.uint8).reshape(*depth.shape, 4)
            cv2.imencode(".png", packed[..., :3])
    return ORBIT / (time.perf_counter() - start)


def first_image_seconds(data) -> float | None:
    """Seconds from the page request to the first preview sent to the tab (None without chromium)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import browser

    from pipelines.viewer.app import Viewer

    if browser.CHROMIUM is None or browser.CHROMEDRIVER is None:
        return None
    viewer = Viewer(data, "127.0.0.1", browser.free_port())
    driver = browser.chromium()
    try:
        start = time.perf_counter()
        driver.get(f"http://127.0.0.1:{viewer.server.get_port()}")
        session = browser.wait(lambda: next(iter(viewer.sessions.values()), None), 60, "the tab")
        browser.wait(lambda: session.shown >= 0 or None, 60, "the first image")
        return time.perf_counter() - start
    finally:
        driver.quit()
        viewer.stop()


def run() -> list[dict]:
    from pipelines.viewer.app import viewer_data

    run_dir = cache_dir() / "viewer_run"
    _fit(run_dir)
    data = viewer_data(run_dir, None, "cpu", preview=192, full=512)
    rows = []
    for side in SIDES:
        rate = preview_rate(data, side)
        size = f"{side} x {round(side * 3 / 4)}"
        rows.append(
            {"benchmark": "narf-view preview", "setting": f"{size}, 2-minute fit", "value": f"{rate:.1f} frames/s"}
        )
    still = 1 / preview_rate(data, 512, still=True)
    rows.append({"benchmark": "narf-view still frame", "setting": "512 x 384", "value": f"{still:.2f} s"})
    first = first_image_seconds(data)
    value = "not measured (no chromium)" if first is None else f"{first:.1f} s"
    rows.append({"benchmark": "narf-view first image", "setting": "page request to first preview", "value": value})
    return rows
