"""Rig calibration files from other tools, read into OpenCV cameras (docs/formats.md §9).

* Qualisys ``.qca.txt`` (XML): focal lengths and centres in 1/64 sensor units, centres offset by the ``fov_video``
  window, the rotation listed by columns, camera centres in mm, cameras looking down -z with y up. Converted as
  Pose2Sim converts it, ``cam_from_world = diag(1, -1, -1) reshape(r11..r33)``, ``t = -cam_from_world centre /
  1000``, except the distortion coefficients: dimensionless, read as written.
* Pose2Sim / Anipose ``.toml``: one table per camera (``matrix``, ``distortions`` k1 k2 p1 p2, Rodrigues
  ``rotation`` and ``translation`` in metres, world to camera).
* EasyMocap ``intri.yml`` / ``extri.yml`` (``pipelines.datasets.easymocap``), ZJU ``annots.npy`` and the folder that
  ``narf-calibrate`` writes (both: ``pipelines.datasets.zju_mocap``).

:func:`read_rig` picks the reader from the path. A camera whose image size the file does not give has width and
height 0 (the videos fill them in).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import cv2
import numpy as np

from fitting.files import atomic_write_bytes
from pipelines.datasets.camera import Camera
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.zju_mocap import read_annots

#: Qualisys stores intrinsics in sub-pixel units: 64 per pixel (as Pose2Sim reads them; binning 1).
QUALISYS_SUBPIXELS = 64.0
#: OpenCV camera axes from Qualisys camera axes (y and z flipped: Qualisys cameras look down -z with y up).
QUALISYS_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


def natural_key(name: str) -> list:
    """Sort key of names in natural order: ``cam2`` before ``cam10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", str(name))]


def _number(path: Path, element, key: str) -> float:
    text = element.get(key)
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise CaptureError(f"{path}: <{element.tag}> {key}={text!r} is not a number") from None
    if not np.isfinite(value):
        raise CaptureError(f"{path}: <{element.tag}> {key} is not finite")
    return value


def _child(path: Path, camera, tag: str):
    found = camera.find(tag)
    if found is None:
        raise CaptureError(f"{path}: camera '{camera.get('serial')}' has no <{tag}>")
    return found


def _rotation(path: Path, name: str, matrix: np.ndarray) -> np.ndarray:
    """A proper rotation (det +1, orthonormal within 1e-3: the files print about 16 digits; a hand-edited matrix is
    refused rather than silently changed)."""
    error = np.abs(matrix @ matrix.T - np.eye(3)).max()
    if error > 1e-3 or np.linalg.det(matrix) < 0:
        raise CaptureError(
            f"{path}: camera '{name}' rotation is not a rotation (det {np.linalg.det(matrix):+.4f}, "
            f"|R R^T - I| = {error:.2g})"
        )
    return matrix


def _qualisys_camera(path: Path, camera) -> Camera:
    name = camera.get("serial") or ""
    window, intrinsic, transform = (_child(path, camera, t) for t in ("fov_video", "intrinsic", "transform"))
    left, top = _number(path, window, "left"), _number(path, window, "top")
    width = int(_number(path, window, "right") - left + 1)
    height = int(_number(path, window, "bottom") - top + 1)
    value = lambda key: _number(path, intrinsic, key) / QUALISYS_SUBPIXELS  # noqa: E731
    K = np.array(
        [
            [value("focalLengthU"), 0.0, value("centerPointU") - left],
            [0.0, value("focalLengthV"), value("centerPointV") - top],
            [0.0, 0.0, 1.0],
        ]
    )
    # Distortion coefficients are read as written (dimensionless), not divided by 64 as Pose2Sim does: the demo's
    # checkerboard shots give k1 = -0.044..-0.048, k2 = 0.09..0.14 per camera against the file's -0.046..-0.048
    # and 0.135..0.140 (docs/formats.md §9).
    raw = lambda key: _number(path, intrinsic, key) if intrinsic.get(key) is not None else 0.0  # noqa: E731
    keys = ("radialDistortion1", "radialDistortion2", "tangentalDistortion1", "tangentalDistortion2")
    dist = np.array([raw(k) for k in (*keys, "radialDistortion3")])
    listed = np.array([_number(path, transform, f"r{i}{j}") for i in (1, 2, 3) for j in (1, 2, 3)]).reshape(3, 3)
    rotation = _rotation(path, name, QUALISYS_TO_OPENCV @ listed)
    centre = np.array([_number(path, transform, k) for k in "xyz"]) / 1000.0
    cam_from_world = np.eye(4)
    cam_from_world[:3, :3], cam_from_world[:3, 3] = rotation, -rotation @ centre
    if width <= 0 or height <= 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CaptureError(f"{path}: camera '{name}' has an empty window or a focal length <= 0")
    return Camera(name, K, dist, cam_from_world, width, height)


def read_qualisys(path: Path) -> list[Camera]:
    """Cameras of a Qualisys ``.qca.txt``: the video cameras (``model`` holding ``video`` or ``none``, as Pose2Sim
    keeps them), in natural order of their serials."""
    path = Path(path)
    try:
        root = ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, UnicodeDecodeError) as err:
        raise CaptureError(f"{path}: not a Qualisys calibration (XML: {err})") from err
    listed = root.findall("cameras/camera")
    if root.tag != "calibration" or not listed:
        raise CaptureError(f"{path}: not a Qualisys calibration (no <calibration><cameras><camera>)")
    video = [c for c in listed if any(m in (c.get("model") or "").lower() for m in ("video", "none"))]
    if not video:
        raise CaptureError(f"{path}: none of its {len(listed)} cameras is a video camera (model 'video' or 'none')")
    cameras = sorted((_qualisys_camera(path, c) for c in video), key=lambda c: natural_key(c.name))
    _check_names(path, cameras)
    return cameras


def write_qualisys(path: Path, cameras: list[Camera]) -> None:
    """Write cameras as a Qualisys ``.qca.txt`` (the inverse of :func:`read_qualisys`; used to test it)."""
    lines = ["<?xml version='1.0' encoding='ASCII'?>", '<calibration type="regular">', "  <cameras>"]
    for cam in cameras:
        listed = QUALISYS_TO_OPENCV @ cam.cam_from_world[:3, :3]
        r = {f"r{i + 1}{j + 1}": repr(float(listed[i, j])) for i in range(3) for j in range(3)}
        centre = [float(v) for v in cam.centre * 1000.0]
        k = (cam.K * QUALISYS_SUBPIXELS).tolist()
        d = [float(v) for v in np.asarray(cam.dist, float)]
        window = f'left="0" top="0" right="{cam.width - 1}" bottom="{cam.height - 1}"'
        rotation = " ".join(f'{key}="{value}"' for key, value in r.items())
        lines += [
            f'    <camera active="1" model="none" serial="{cam.name}">',
            f"      <fov_video {window}/>",
            f'      <transform {rotation} x="{centre[0]!r}" y="{centre[1]!r}" z="{centre[2]!r}"/>',
            f'      <intrinsic focalLengthU="{k[0][0]!r}" focalLengthV="{k[1][1]!r}" centerPointU="{k[0][2]!r}" '
            f'centerPointV="{k[1][2]!r}" radialDistortion1="{d[0]!r}" radialDistortion2="{d[1]!r}" '
            f'radialDistortion3="{d[4]!r}" tangentalDistortion1="{d[2]!r}" tangentalDistortion2="{d[3]!r}"/>',
            "    </camera>",
        ]
    lines += ["  </cameras>", "</calibration>", ""]
    atomic_write_bytes(Path(path), "\n".join(lines).encode("ascii"))


def _toml_array(path: Path, name: str, table: dict, key: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        value = np.asarray(table[key], dtype=np.float64)
    except KeyError:
        raise CaptureError(f"{path}: camera '{name}' has no '{key}'") from None
    except (TypeError, ValueError):
        raise CaptureError(f"{path}: camera '{name}' {key} is not numeric") from None
    if value.shape != shape or not np.isfinite(value).all():
        raise CaptureError(f"{path}: camera '{name}' {key} must be finite with shape {shape}, got {value.shape}")
    return value


def read_toml(path: Path) -> list[Camera]:
    """Cameras of a Pose2Sim / Anipose calibration ``.toml`` (every table but ``metadata``), in file order."""
    import tomllib

    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise CaptureError(f"{path}: not a TOML file ({err})") from err
    cameras = []
    for key, table in data.items():
        if key == "metadata" or not isinstance(table, dict):
            continue
        name = str(table.get("name", key))
        if table.get("fisheye", False):
            raise CaptureError(f"{path}: camera '{name}' is a fisheye camera, which this tool does not model")
        K = _toml_array(path, name, table, "matrix", (3, 3))
        dist = np.pad(_toml_array(path, name, table, "distortions", (4,)), (0, 1))
        rotation, _ = cv2.Rodrigues(_toml_array(path, name, table, "rotation", (3,)))
        width, height = (int(v) for v in _toml_array(path, name, table, "size", (2,)))
        cam_from_world = np.eye(4)
        cam_from_world[:3, :3] = rotation
        cam_from_world[:3, 3] = _toml_array(path, name, table, "translation", (3,))
        cameras.append(Camera(name, K, dist, cam_from_world, width, height))
    if not cameras:
        raise CaptureError(f"{path}: no camera tables (expected [cam_01] ... with matrix, rotation, translation)")
    _check_names(path, cameras)
    return cameras


def _check_names(path: Path, cameras: list[Camera]) -> None:
    names = [c.name for c in cameras]
    if len(set(names)) != len(names) or not all(names):
        raise CaptureError(f"{path}: camera names are empty or repeat: {names}")


def read_rig(path: str | Path) -> list[Camera]:
    """Cameras of any calibration this tool reads, chosen by the path (module docstring), each with a usable
    pinhole: finite, positive focal lengths, last row of K 0 0 1."""
    path = Path(path)
    cameras = _read_any_rig(path)
    for camera in cameras:
        K = np.asarray(camera.K, dtype=np.float64)
        if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1])):
            raise CaptureError(
                f"{path}: camera '{camera.name}' has no usable intrinsics (K = {K.round(3).tolist()}: the focal "
                "lengths must be positive and the last row 0 0 1)"
            )
    return cameras


def _read_any_rig(path: Path) -> list[Camera]:
    from pipelines.datasets.easymocap import read_easymocap_cameras

    if path.is_dir():
        if (path / "intri.yml").is_file() and (path / "extri.yml").is_file():
            return read_easymocap_cameras(path)
        if (path / "annots.npy").is_file():
            return read_annots(path / "annots.npy", image_size=(0, 0), check_folders=False)[0]
        raise CaptureError(f"{path}: no calibration in this folder (intri.yml + extri.yml, or annots.npy)")
    if not path.is_file():
        raise CaptureError(f"{path}: no such calibration file")
    name = path.name.lower()
    if name.endswith((".qca.txt", ".qca", ".xml")):
        return read_qualisys(path)
    if name.endswith(".toml"):
        return read_toml(path)
    if name in ("intri.yml", "extri.yml"):
        return read_easymocap_cameras(path.parent)
    if name.endswith(".npy"):
        return read_annots(path, image_size=(0, 0), check_folders=False)[0]
    raise CaptureError(
        f"{path}: unknown calibration format (read: Qualisys .qca.txt, Pose2Sim/Anipose .toml, EasyMocap "
        "intri.yml/extri.yml, ZJU annots.npy, a narf-calibrate output folder)"
    )
