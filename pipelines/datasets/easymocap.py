"""EasyMocap camera files: ``intri.yml`` (K, dist, image size) and ``extri.yml`` (R, Rot, T), OpenCV FileStorage.

The layout and the readers' habits are described in ``docs/formats.md`` (EasyMocap cameras). Files are written as
EasyMocap's own writer writes them (text, CRLF lines, quoted ``names``), not through ``cv2.FileStorage``, whose
writer refuses keys such as ``K_Camera (1)``: names with spaces and brackets survive a write-read round trip.
They are read with ``cv2.FileStorage`` as EasyMocap reads them: ``names`` entries ``none`` are skipped, numeric
names written without quotes become their integer text, the rotation is rebuilt from ``R_`` (Rodrigues; ``Rot_``
when ``R_`` is absent), and ``dist_`` falls back to ``D_`` and then to no distortion.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from fitting.files import atomic_write_bytes
from pipelines.datasets.camera import Camera
from pipelines.datasets.errors import CaptureError

#: Characters a camera name cannot hold: they would end the YAML key or the quoted ``names`` entry.
_FORBIDDEN = set('":#\\\r\n\t')
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


def _matrix(key: str, value: np.ndarray) -> list[str]:
    value = np.atleast_2d(np.asarray(value, dtype=np.float64))
    data = ", ".join(repr(float(v)) for v in value.reshape(-1))  # shortest text that reads back exactly
    return [f"{key}: !!opencv-matrix", f"  rows: {value.shape[0]}", f"  cols: {value.shape[1]}", "  dt: d"] + [
        f"  data: [{data}]"
    ]


def _check_name(name: str) -> None:
    if not name or name != name.strip() or _FORBIDDEN & set(name) or name.lower() == "none":
        raise ValueError(f"camera name {name!r} cannot be written to EasyMocap YAML (empty, 'none', or one of \" : #)")


def _yaml_text(names: list[str], blocks: list[list[str]]) -> bytes:
    lines = ["%YAML:1.0", "---", "names:", *[f'  - "{n}"' for n in names]]
    lines += [line for block in blocks for line in block]
    return ("\r\n".join(lines) + "\r\n").encode()


def write_easymocap_cameras(folder: Path, cameras: list[Camera]) -> None:
    """Write EasyMocap ``intri.yml`` / ``extri.yml`` (``R_`` Rodrigues and ``Rot_`` consistent, T in metres).

    ``H_`` / ``W_`` are written only when the camera knows its image size (never as 0). Each file is replaced
    atomically.
    """
    folder = Path(folder)
    names = [c.name for c in cameras]
    for name in names:
        _check_name(name)
    if len(set(names)) != len(names):
        raise ValueError(f"camera names repeat: {names}")
    intri, extri = [], []
    for cam in cameras:
        size = [f"H_{cam.name}: {int(cam.height)}", f"W_{cam.name}: {int(cam.width)}"] if cam.width > 0 else []
        intri.append(_matrix(f"K_{cam.name}", cam.K) + _matrix(f"dist_{cam.name}", cam.dist.reshape(1, 5)) + size)
        rotation = cam.cam_from_world[:3, :3]
        extri.append(
            _matrix(f"R_{cam.name}", cv2.Rodrigues(rotation)[0])
            + _matrix(f"Rot_{cam.name}", rotation)
            + _matrix(f"T_{cam.name}", cam.cam_from_world[:3, 3:4])
        )
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(folder / "intri.yml", _yaml_text(names, intri))
    atomic_write_bytes(folder / "extri.yml", _yaml_text(names, extri))


def _open(path: Path) -> cv2.FileStorage:
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ) if path.is_file() else None
    except (cv2.error, SystemError) as err:  # OpenCV 5 raises SystemError on some malformed files
        raise CaptureError(f"{path}: not an OpenCV YAML file ({str(err).strip().splitlines()[-1]})") from err
    if storage is None or not storage.isOpened():
        raise CaptureError(f"{path}: missing or not an OpenCV YAML file")
    return storage


def _names(storage: cv2.FileStorage, path: Path) -> list[str]:
    node = storage.getNode("names")
    if node.empty() or not node.isSeq():
        raise CaptureError(f"{path}: no 'names' list")
    out = []
    for i in range(node.size()):
        entry = node.at(i)
        out.append(entry.string() if entry.isString() else str(int(entry.real())))
    return out


def _mat(storage: cv2.FileStorage, *keys: str) -> np.ndarray | None:
    for key in keys:
        node = storage.getNode(key)
        if not node.empty() and node.isMap():
            return node.mat()
    return None


def _size(storage: cv2.FileStorage, key: str) -> int:
    node = storage.getNode(key)
    return int(node.real()) if not node.empty() and (node.isReal() or node.isInt()) else 0


def _camera(name: str, intri: cv2.FileStorage, extri: cv2.FileStorage, folder: Path) -> Camera | None:
    K, rvec, rot = _mat(intri, f"K_{name}"), _mat(extri, f"R_{name}"), _mat(extri, f"Rot_{name}")
    tvec = _mat(extri, f"T_{name}")
    if K is None or tvec is None or (rvec is None and rot is None):
        return None
    dist = _mat(intri, f"dist_{name}", f"D_{name}")
    dist = np.zeros(5) if dist is None else np.pad(dist.reshape(-1), (0, 5))[:5]
    rotation = cv2.Rodrigues(rvec.reshape(3, 1).astype(np.float64))[0] if rvec is not None else rot
    values = {"K": K, "dist": dist, "R": rotation, "T": tvec}
    shapes = {"K": (3, 3), "dist": (5,), "R": (3, 3), "T": (3,)}
    for key, value in values.items():
        if value.size != int(np.prod(shapes[key])) or not np.isfinite(value).all():
            raise CaptureError(f"{folder}: camera '{name}': {key} is malformed (shape {value.shape}, or NaN/inf)")
    if abs(np.linalg.det(K)) < 1e-9 or abs(abs(np.linalg.det(rotation)) - 1) > 1e-3:
        raise CaptureError(f"{folder}: camera '{name}': singular K or a rotation that is not orthonormal")
    cam_from_world = np.eye(4)
    cam_from_world[:3, :3] = rotation
    cam_from_world[:3, 3] = tvec.reshape(3)
    width, height = _size(intri, f"W_{name}"), _size(intri, f"H_{name}")
    return Camera(name, K.reshape(3, 3).astype(np.float64), dist.astype(np.float64), cam_from_world, width, height)


def _first_image_size(folder: Path) -> tuple[int, int] | None:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if folder.is_dir() else []
    if not files:
        return None
    image = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CaptureError(f"{files[0]}: unreadable image")
    return image.shape[1], image.shape[0]


def read_easymocap_cameras(folder: Path, images: Path | None = None) -> list[Camera]:
    """Read EasyMocap ``intri.yml`` / ``extri.yml`` as EasyMocap does (module docstring).

    Args:
        folder: the folder holding both files.
        images: optional image root with one sub-folder per camera name (``images/<name>/*.jpg``); the size of
            its first image is checked against ``H_`` / ``W_``, or fills them in when the file lacks them.

    Returns:
        The cameras in ``names`` order, without the skipped ones (one warning on stderr says how many).
        A camera without ``H_`` / ``W_`` (and no image to measure) has width = height = 0.
    """
    folder = Path(folder)
    intri, extri = _open(folder / "intri.yml"), _open(folder / "extri.yml")
    names = _names(intri, folder / "intri.yml")
    cameras, skipped = [], [n for n in names if n == "none"]
    for name in (n for n in names if n != "none"):
        try:
            camera = _camera(name, intri, extri, folder)
        except (cv2.error, SystemError) as err:
            reason = str(err).strip().splitlines()[-1]
            raise CaptureError(
                f"{folder}: camera '{name}' cannot be read from intri.yml / extri.yml ({reason})"
            ) from err
        if camera is None:
            skipped.append(name)
            continue
        measured = _first_image_size(Path(images) / name) if images is not None else None
        if measured is not None and camera.width > 0 and measured != (camera.width, camera.height):
            raise CaptureError(
                f"{folder / 'intri.yml'}: camera '{name}' is {camera.width}x{camera.height} (W_/H_) but its images "
                f"in {Path(images) / name} are {measured[0]}x{measured[1]}"
            )
        if measured is not None and camera.width == 0:
            camera = Camera(camera.name, camera.K, camera.dist, camera.cam_from_world, *measured)
        cameras.append(camera)
    if not cameras:  # one line: the error says what the note would have said
        also = f" (all {len(names)} camera names are 'none' or lack K/R/T)" if skipped else ""
        raise CaptureError(f"{folder}: no camera with K in intri.yml and R/T in extri.yml{also}")
    if skipped:
        print(
            f"{Path(sys.argv[0]).name}: note: {folder}: skipped {len(skipped)} of {len(names)} camera names ('none' "
            "or without K/R/T), as EasyMocap does",
            file=sys.stderr,
        )
    return cameras
