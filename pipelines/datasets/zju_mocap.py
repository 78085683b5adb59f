"""ZJU-MoCap (CoreView_*) reader and writer, exactly as docs/formats.md §1.

The reader follows the Neural Body loader order (§1.7): read /255 -> mask from ``mask_cihp`` (and/or ``mask``)
-> undistort image and mask -> resize by ``ratio`` (INTER_AREA / NEAREST) -> background outside the mask ->
scale K. The 5x5 dilate-minus-erode boundary band is returned separately so that losses can skip it.
Project decision: the mask is undistorted with nearest-neighbour remapping (neuralbody interpolates its uint8
labels bilinearly, which invents intermediate labels on edges).
"""

from __future__ import annotations

import pickle
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from fitting.files import atomic_write_bytes
from pipelines.datasets.camera import Camera
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.safe_pickle import load_npy, load_npy_object


@dataclass(frozen=True)
class SmplParams:
    """One frame's SMPL fit (EasyMocap convention ``V_world = R(Rh) X + Th``): poses (72,), Rh (3,), Th (3,),
    shapes (10,), float32."""

    poses: np.ndarray
    rh: np.ndarray
    th: np.ndarray
    shapes: np.ndarray


@dataclass
class Frame:
    """One (frame, camera) view after loading.

    Attributes:
        frame_index: 0-based frame index.
        camera_index: index into the annots camera list.
        image: (H, W, 3) float32 RGB in [0, 1], background composited.
        mask: (H, W) float32 in {0, 1}.
        band: (H, W) bool, the 5-px boundary band (skipped by the mask loss).
        labels: (H, W) uint8 CIHP labels (0 where unknown).
        camera: the camera of this image (undistorted, resized).
        params: the frame's SMPL parameters.
        image_path: source image.
        unknown: (H, W) bool pixels whose owner is unknown (another person in front of this one: a prepared
            capture's ``mask_unknown/``), outside ``mask`` and inside ``band``; no loss draws them. None: no such file.
    """

    frame_index: int
    camera_index: int
    image: np.ndarray
    mask: np.ndarray
    band: np.ndarray
    labels: np.ndarray
    camera: Camera
    params: SmplParams
    image_path: Path = field(default=Path())
    unknown: np.ndarray | None = None


_313_PATTERN = re.compile(r"^(?P<prefix>.+?)_(?P<index>\d{4})_[^_]*$")


def param_index_from_image(rel_path: str) -> tuple[int, int]:
    """(frame_index, params file index) of an image path in ``annots['ims']`` (§1.2).

    Standard subjects: ``Camera_B1/000012.jpg`` -> (12, 12). 313/315: the fifth underscore-separated field of
    ``CoreView_313_Camera_(1)_0013_<timestamp>.jpg`` is 1-based -> (12, 13).
    """
    stem = Path(rel_path).stem
    if stem.isdigit():
        return int(stem), int(stem)
    fields = stem.split("_")
    if len(fields) >= 5 and fields[4].isdigit():
        one_based = int(fields[4])
        return one_based - 1, one_based
    raise CaptureError(f"cannot read a frame index from image name '{rel_path}'")


def _read_npy_dict(path: Path) -> dict:
    if not path.is_file():
        raise CaptureError(f"{path}: missing")
    try:
        value = load_npy_object(path)  # a pickled dict by format, read without running code (safe_pickle)
        return value.item() if value.dtype == object and value.shape == () else {"__array__": value}
    except (OSError, ValueError, EOFError, pickle.UnpicklingError) as err:
        raise CaptureError(f"{path}: unreadable ({err})") from err


def read_params(path: Path) -> SmplParams:
    """Read ``params/{i}.npy`` or ``new_params/{i}.npy``; check keys, shapes and finiteness."""
    data = _read_npy_dict(path)
    want = {"poses": 72, "Rh": 3, "Th": 3, "shapes": 10}
    values = {}
    for key, size in want.items():
        if key not in data:
            raise CaptureError(f"{path}: missing key '{key}' (has {sorted(data)})")
        try:
            arr = np.asarray(data[key], dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise CaptureError(f"{path}: '{key}' is not numeric ({err})") from None
        if arr.size != size:
            raise CaptureError(f"{path}: '{key}' has shape {arr.shape}, expected (1, {size})")
        if not np.isfinite(arr).all():
            raise CaptureError(f"{path}: '{key}' contains NaN or infinite values")
        values[key] = arr.reshape(size).astype(np.float32)
    return SmplParams(values["poses"], values["Rh"], values["Th"], values["shapes"])


def write_params(path: Path, params: SmplParams) -> None:
    """Write an EasyMocap/ZJU params file: a dict of (1, n) float64 arrays."""
    data = {
        "poses": params.poses[None].astype(np.float64),
        "Rh": params.rh[None].astype(np.float64),
        "Th": params.th[None].astype(np.float64),
        "shapes": params.shapes[None].astype(np.float64),
    }
    _save_npy(path, np.array(data, dtype=object))


BODY_SURFACE = "body_surface.npy"
MAX_DISPLACEMENT = 0.2  # metres: a displacement beyond this is no garment, but a broken file


def read_body_surface(path: Path, n_vertices: int) -> np.ndarray:
    """(n_vertices,) float32 metres: each template vertex's displacement along its normal (docs/formats.md §1.13)."""
    try:
        data = load_npy(path)
    except (OSError, ValueError) as err:
        raise CaptureError(f"{path}: unreadable ({err})") from None
    if data.shape != (n_vertices,) or data.dtype.kind != "f":
        raise CaptureError(f"{path}: expected ({n_vertices},) floats, got {data.dtype} {data.shape}")
    if not np.isfinite(data).all() or np.abs(data).max() > MAX_DISPLACEMENT:
        raise CaptureError(f"{path}: displacements must be finite and within {MAX_DISPLACEMENT} m")
    return data.astype(np.float32)


def write_body_surface(path: Path, displacement: np.ndarray) -> None:
    """Write :func:`read_body_surface`'s file."""
    _save_npy(path, np.asarray(displacement, np.float32))


def _save_npy(path: Path, array: np.ndarray) -> None:
    import io

    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=True)
    atomic_write_bytes(Path(path), buffer.getvalue())


def write_annots(path: Path, cameras: list[Camera], ims: list[list[str]]) -> None:
    """Write ``annots.npy``: cams K, D (5,1), R, T (3,1) in millimetres; ims per frame."""
    cams = {
        "K": [c.K.astype(np.float64) for c in cameras],
        "D": [c.dist.reshape(5, 1) for c in cameras],
        "R": [c.cam_from_world[:3, :3].copy() for c in cameras],
        "T": [c.cam_from_world[:3, 3:4] * 1000.0 for c in cameras],
    }
    for frame_ims in ims:
        if len(frame_ims) != len(cameras):
            raise ValueError(f"each ims entry must list {len(cameras)} paths, got {len(frame_ims)}")
    _save_npy(path, np.array({"cams": cams, "ims": [{"ims": list(f)} for f in ims]}, dtype=object))


def _orthonormalise(rotation: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(rotation)
    fixed = u @ vt
    if np.linalg.det(fixed) < 0:  # keep a proper rotation (SURREAL-style det -1 matrices are not ZJU's)
        u[:, -1] *= -1
        fixed = u @ vt
    return fixed


def _check_camera(path: Path, c: int, cams: dict) -> None:
    """Shapes, finiteness, an invertible K and a rotation close to orthonormal (det within 1e-3 of +1)."""
    sizes = {"K": 9, "D": (4, 5, 8), "R": 9, "T": 3}
    for key, size in sizes.items():
        try:
            value = np.asarray(cams[key][c], dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise CaptureError(f"{path}: cams['{key}'][{c}] is not numeric ({err})") from err
        if value.size not in (size if isinstance(size, tuple) else (size,)):
            raise CaptureError(f"{path}: cams['{key}'][{c}] has shape {value.shape}")
        if not np.isfinite(value).all():
            raise CaptureError(f"{path}: cams['{key}'][{c}] contains NaN or infinite values")
    K, R = np.asarray(cams["K"][c], np.float64).reshape(3, 3), np.asarray(cams["R"][c], np.float64).reshape(3, 3)
    if abs(np.linalg.det(K)) < 1e-9:
        raise CaptureError(f"{path}: cams['K'][{c}] is singular")
    if abs(np.linalg.det(R) - 1) > 1e-3:  # det -1 is a reflection: a left-handed camera no loader expects
        raise CaptureError(f"{path}: cams['R'][{c}] is not a rotation (det {np.linalg.det(R):.4g}, expected +1)")


def read_annots(
    path: Path, image_size: tuple[int, int] | None = None, check_folders: bool = True
) -> tuple[list[Camera], list[list[str]]]:
    """Read ``annots.npy`` into cameras (T converted to metres, R re-orthonormalised) and per-frame image paths.

    Args:
        path: the annots file.
        image_size: (width, height) of the images; ``None`` reads the first image of each camera.
        check_folders: require every camera's image folder (off for calibration, which needs only calib/).
    """
    data = _read_npy_dict(Path(path))
    if "cams" not in data or "ims" not in data:
        raise CaptureError(f"{path}: expected keys 'cams' and 'ims', got {sorted(data)}")
    cams = data["cams"]
    for key in ("K", "D", "R", "T"):
        if key not in cams:
            raise CaptureError(f"{path}: cams lacks '{key}'")
    n_cams = len(cams["K"])
    if not all(len(cams[k]) == n_cams for k in ("D", "R", "T")):
        raise CaptureError(
            f"{path}: cams K/D/R/T list different numbers of cameras ({[len(cams[k]) for k in ('K', 'D', 'R', 'T')]})"
        )
    ims = [list(entry["ims"]) for entry in data["ims"]]
    for f, entry in enumerate(ims):
        if len(entry) != n_cams:
            raise CaptureError(f"{path}: ims[{f}] lists {len(entry)} images but cams has {n_cams} cameras")
    root = Path(path).parent
    cameras = []
    for c in range(n_cams):
        folder = Path(ims[0][c]).parent.as_posix() if ims else f"camera_{c}"
        if check_folders and ims and not (root / folder).is_dir():
            raise CaptureError(f"{root / folder}: camera folder listed in {Path(path).name} is missing")
        if image_size is None:
            first = root / ims[0][c]
            probe = cv2.imread(str(first), cv2.IMREAD_UNCHANGED)
            if probe is None:
                raise CaptureError(f"{first}: missing or unreadable image (camera {c} of {path})")
            width, height = probe.shape[1], probe.shape[0]
        else:
            width, height = image_size
        _check_camera(path, c, cams)
        cam_from_world = np.eye(4)
        cam_from_world[:3, :3] = _orthonormalise(np.asarray(cams["R"][c], dtype=np.float64).reshape(3, 3))
        cam_from_world[:3, 3] = np.asarray(cams["T"][c], dtype=np.float64).reshape(3) / 1000.0
        dist = np.asarray(cams["D"][c], dtype=np.float64).reshape(-1)
        dist = np.pad(dist, (0, max(0, 5 - dist.size)))[:5]
        cameras.append(
            Camera(
                folder, np.asarray(cams["K"][c], dtype=np.float64).reshape(3, 3), dist, cam_from_world, width, height
            )
        )
    return cameras, ims


def boundary_band(mask: np.ndarray, width: int = 5) -> np.ndarray:
    """The ``width x width`` dilate-minus-erode ring of a binary mask (bool)."""
    kernel = np.ones((width, width), np.uint8)
    mask_u8 = (mask > 0).astype(np.uint8)
    return (cv2.dilate(mask_u8, kernel) - cv2.erode(mask_u8, kernel)) > 0
