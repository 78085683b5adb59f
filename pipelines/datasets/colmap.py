"""COLMAP sparse models of a calibrated rig, written and read by pycolmap (COLMAP's own reader and writer).

A camera becomes a COLMAP camera of model ``OPENCV`` (fx fy cx cy k1 k2 p1 p2) when its k3 is 0, else
``FULL_OPENCV`` (fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6, k4..k6 = 0), so no distortion term is dropped; each camera's
image is registered with its ``cam_from_world`` (a trivial rig and frame per camera, as pycolmap 4 requires).
Image names are ``<camera name>.jpg``. docs/formats.md, "COLMAP model".
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipelines.datasets.camera import Camera
from pipelines.datasets.errors import CaptureError

#: COLMAP camera models read back as OpenCV cameras: their parameters after fx, fy, cx, cy, in OpenCV's order.
READABLE = {"PINHOLE": 0, "OPENCV": 4, "FULL_OPENCV": 8}


def _pycolmap():
    import pycolmap

    pycolmap.logging.minloglevel = 2  # errors only (glog levels: 0 info, 1 warning, 2 error)
    return pycolmap


def write_colmap_model(folder: Path, cameras: list[Camera], binary: bool = False) -> Path:
    """Write ``cameras`` as a COLMAP model (text: cameras.txt, images.txt, rigs.txt, frames.txt, points3D.txt; or
    the ``.bin`` files) into ``folder``; camera and image ids are 1..N in list order."""
    pycolmap = _pycolmap()
    model = pycolmap.Reconstruction()
    for index, cam in enumerate(cameras, start=1):
        dist = np.zeros(8)
        dist[: len(cam.dist)] = np.asarray(cam.dist, dtype=np.float64).ravel()[:8]
        full = bool(np.any(dist[4:]))
        params = [cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2], *(dist if full else dist[:4])]
        model.add_camera_with_trivial_rig(
            pycolmap.Camera(
                model="FULL_OPENCV" if full else "OPENCV",
                width=int(cam.width),
                height=int(cam.height),
                params=params,
                camera_id=index,
            )
        )
        image = pycolmap.Image(name=f"{cam.name.replace(' ', '_')}.jpg", camera_id=index, image_id=index)
        pose = pycolmap.Rigid3d(np.asarray(cam.cam_from_world, dtype=np.float64)[:3, :4])
        model.add_image_with_trivial_frame(image, pose)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (model.write_binary if binary else model.write_text)(str(folder))
    return folder


def read_colmap_cameras(folder: Path) -> list[Camera]:
    """The registered images of a COLMAP model (text or binary) as OpenCV cameras, in image-id order; a camera name
    is its image name without the suffix. Models other than PINHOLE, OPENCV and FULL_OPENCV are refused."""
    pycolmap = _pycolmap()
    folder = Path(folder)
    if not folder.is_dir():
        raise CaptureError(f"{folder}: no COLMAP model folder")
    model = pycolmap.Reconstruction()
    try:
        model.read(str(folder))
    except Exception as err:  # pycolmap raises ValueError or RuntimeError with COLMAP's message
        raise CaptureError(f"{folder}: not a readable COLMAP model ({str(err).strip().splitlines()[0]})") from err
    cameras = []
    for image_id in sorted(model.reg_image_ids()):
        image = model.image(image_id)
        camera = model.camera(image.camera_id)
        name = camera.model.name
        if name not in READABLE:
            raise CaptureError(f"{folder}: camera {image.camera_id} is {name}; readable: {', '.join(READABLE)}")
        params = np.asarray(camera.params, dtype=np.float64)
        K = np.array([[params[0], 0, params[2]], [0, params[1], params[3]], [0, 0, 1]])
        dist = np.zeros(5)
        extra = params[4 : 4 + READABLE[name]]
        dist[: min(5, len(extra))] = extra[:5]
        if np.any(extra[5:]):
            raise CaptureError(f"{folder}: camera {image.camera_id} has k4..k6 (rational model); we carry k1..k3")
        cam_from_world = np.eye(4)
        cam_from_world[:3] = image.cam_from_world().matrix()
        cameras.append(Camera(Path(image.name).stem, K, dist, cam_from_world, camera.width, camera.height))
    return cameras
