"""EasyMocap camera files: ``intri.yml`` (K, dist, image size) and ``extri.yml`` (R, Rot, T), OpenCV FileStorage.

The layout is described in ``docs/formats.md`` (EasyMocap cameras).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pipelines.datasets.zju_mocap import Camera, CaptureError


def write_easymocap_cameras(folder: Path, cameras: list[Camera]) -> None:
    """Write EasyMocap ``intri.yml`` / ``extri.yml`` (OpenCV FileStorage; R_ Rodrigues and Rot_ consistent)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = [c.name.replace(" ", "_").replace("(", "").replace(")", "") for c in cameras]
    for kind in ("intri", "extri"):
        tmp = folder / f".{kind}.tmp.yml"
        storage = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        storage.startWriteStruct("names", cv2.FileNode_SEQ)
        for name in names:
            storage.write("", name)
        storage.endWriteStruct()
        for name, cam in zip(names, cameras):
            if kind == "intri":
                storage.write(f"K_{name}", cam.K)
                storage.write(f"dist_{name}", cam.dist.reshape(1, 5))
                storage.write(f"H_{name}", int(cam.height))
                storage.write(f"W_{name}", int(cam.width))
            else:
                rotation = cam.cam_from_world[:3, :3]
                storage.write(f"R_{name}", cv2.Rodrigues(rotation)[0])
                storage.write(f"Rot_{name}", rotation)
                storage.write(f"T_{name}", cam.cam_from_world[:3, 3:4].copy())
        storage.release()
        tmp.replace(folder / f"{kind}.yml")


def read_easymocap_cameras(folder: Path) -> list[Camera]:
    """Read EasyMocap ``intri.yml`` / ``extri.yml`` (rotation rebuilt from ``R_`` as EasyMocap does)."""
    folder = Path(folder)
    files = {}
    for kind in ("intri", "extri"):
        path = folder / f"{kind}.yml"
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ) if path.is_file() else None
        if storage is None or not storage.isOpened():
            raise CaptureError(f"{path}: missing or not an OpenCV YAML file")
        files[kind] = storage
    names_node = files["intri"].getNode("names")
    names = [names_node.at(i).string() for i in range(names_node.size())]
    cameras = []
    for name in names:
        K = files["intri"].getNode(f"K_{name}").mat()
        dist = files["intri"].getNode(f"dist_{name}").mat()
        if dist is None:
            dist = files["intri"].getNode(f"D_{name}").mat()
        rvec, tvec = files["extri"].getNode(f"R_{name}").mat(), files["extri"].getNode(f"T_{name}").mat()
        if K is None or dist is None or rvec is None or tvec is None:
            raise CaptureError(f"{folder}: camera '{name}' lacks K/dist in intri.yml or R/T in extri.yml")
        cam_from_world = np.eye(4)
        cam_from_world[:3, :3] = cv2.Rodrigues(rvec)[0]
        cam_from_world[:3, 3] = tvec.reshape(3)
        width = int(files["intri"].getNode(f"W_{name}").real() or 0)
        height = int(files["intri"].getNode(f"H_{name}").real() or 0)
        cameras.append(Camera(name, K, dist.reshape(-1)[:5], cam_from_world, width, height))
    return cameras
