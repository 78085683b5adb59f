"""THUman (DeepHuman) as NARF uses it (``docs/formats.md §6``): raw items and NARF's ``render_128`` splits.

Raw item: ``results_<tag>_<date>_<name>_<n>_<F|M>/<frame>/`` with ``mesh.obj`` (vertex colours as
``v x y z r g b``), ``smpl.obj``, ``cam.txt`` (4 x 4 world -> depth camera) and ``smpl_params.txt`` (CRLF text:
``ShapeParams``, 10 betas, ``RootTransformation``, a 4 x 4 [R | t], ``JointRotations``, 72 values one per line).
The scan is the SMPL body placed as ``M(theta, beta) R^T + t``, a rotation about the SMPL origin.

``render_128``: ``color/color_%08d.png`` (RGBA written by OpenCV, so BGRA on disk; alpha is the mask),
``color/pose_to_camera_%08d.npy`` and ``color/pose_to_world_%08d.npy`` (24, 4, 4) per render,
``bone_params/bone_params_%08d.npy`` (24, 4, 4) per mesh; render index = renders_per_mesh * mesh + view;
K = [[256, 0, 64], [0, 256, 64], [0, 0, 1]] with pixel centres at +0.5 (``THUMAN_K`` is converted).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipelines.datasets.errors import CaptureError
from pipelines.datasets.images import read_image
from pipelines.datasets.safe_pickle import load_npy

RENDER_SIZE = 128
#: NARF's render_128 intrinsics (pixel centres at +0.5) converted to the project's convention (c - 0.5).
THUMAN_K = np.array([[256.0, 0.0, 63.5], [0.0, 256.0, 63.5], [0.0, 0.0, 1.0]])
_ITEM_PATTERN = re.compile(r"^results_.+_(?P<gender>[FM])$")


@dataclass
class ThumanView:
    """One render as a training or evaluation view (the fields ``fitting.data.TrainingSet`` reads): image (H, W, 3)
    in [0, 1] on black, mask (H, W), band (H, W) bool (no boundary band on renders: all False) and its camera."""

    image: np.ndarray
    mask: np.ndarray
    band: np.ndarray
    camera: object


@dataclass(frozen=True)
class ThumanSmpl:
    """One raw item's SMPL fit: betas (10,), pose (72,) axis-angle, world_from_smpl (4, 4) = [R | t]."""

    betas: np.ndarray
    pose: np.ndarray
    world_from_smpl: np.ndarray


@dataclass(frozen=True)
class ColoredMesh:
    """A scan: vertices (V, 3) metres, colours (V, 3) in [0, 1], triangles (F, 3) 0-based."""

    vertices: np.ndarray
    colors: np.ndarray
    faces: np.ndarray


def _floats(line: str, path: Path, line_no: int, count: int | None = None) -> list[float]:
    try:
        values = [float(v) for v in line.split()]
    except ValueError as err:
        raise CaptureError(f"{path}: line {line_no} is not a list of numbers ({line.strip()[:40]!r})") from err
    if count is not None and len(values) != count:
        raise CaptureError(f"{path}: line {line_no} has {len(values)} numbers, expected {count}")
    return values


def read_smpl_params_txt(path: str | Path) -> ThumanSmpl:
    """Read a THUman ``smpl_params.txt`` (CRLF or LF line ends; module docstring).

    Raises:
        CaptureError: missing file, missing section header, or a wrong count of numbers (naming the line).
    """
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: no such smpl_params.txt")
    lines = [line.strip() for line in path.read_text(errors="replace").splitlines()]
    headers = {"ShapeParams": 0, "RootTransformation": 2, "JointRotations": 7}
    for name, index in headers.items():
        if len(lines) <= index or lines[index] != name:
            found = lines[index][:40] if len(lines) > index else "end of file"
            raise CaptureError(f"{path}: line {index + 1} should be '{name}', found {found!r}")
    betas = np.array(_floats(lines[1], path, 2, 10))
    root = np.array([_floats(lines[3 + r], path, 4 + r, 4) for r in range(4)])
    pose_lines = [line for line in lines[8:] if line]
    if len(pose_lines) != 72:
        raise CaptureError(f"{path}: {len(pose_lines)} joint rotation values after 'JointRotations', expected 72")
    pose = np.array([_floats(line, path, 9 + i, 1)[0] for i, line in enumerate(pose_lines)])
    if not np.allclose(root[3], [0, 0, 0, 1]):
        raise CaptureError(f"{path}: RootTransformation's last row is {root[3].tolist()}, expected [0, 0, 0, 1]")
    return ThumanSmpl(betas, pose, root)


def read_cam_txt(path: str | Path) -> np.ndarray:
    """A raw item's ``cam.txt``: the (4, 4) world -> depth-camera matrix."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: no such cam.txt")
    rows = [_floats(line, path, i + 1, 4) for i, line in enumerate(path.read_text().splitlines()) if line.strip()]
    if len(rows) != 4:
        raise CaptureError(f"{path}: {len(rows)} rows, expected a 4x4 matrix")
    return np.array(rows)


def read_colored_obj(path: str | Path) -> ColoredMesh:
    """A vertex-coloured OBJ (``v x y z r g b``, faces ``f a b c`` with optional ``/vt/vn``, polygons fanned).

    A vertex line without colours is 0.5 grey, as THUman's tools read it; a mesh with no colour at all is an
    error, because an avatar cannot be rendered from it.

    Raises:
        CaptureError: missing file, malformed line, face index out of range, or no vertex colours.
    """
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: no such mesh")
    vertices, colors, faces = [], [], []
    with open(path, errors="replace") as handle:
        for line_no, line in enumerate(handle, 1):
            if line.startswith("v "):
                values = _floats(line[2:], path, line_no)
                if len(values) not in (3, 6):
                    raise CaptureError(f"{path}: line {line_no}: a vertex has {len(values)} numbers, expected 3 or 6")
                vertices.append(values[:3])
                colors.append(values[3:] if len(values) == 6 else [np.nan] * 3)
            elif line.startswith("f "):
                try:
                    ids = [int(token.split("/")[0]) for token in line.split()[1:]]
                except ValueError as err:
                    raise CaptureError(f"{path}: line {line_no} is not a face ({line.strip()[:40]!r})") from err
                faces += [[ids[0], ids[k], ids[k + 1]] for k in range(1, len(ids) - 1)]
    vertices, colors = np.array(vertices, np.float64).reshape(-1, 3), np.array(colors, np.float64).reshape(-1, 3)
    if np.isnan(colors).all():
        raise CaptureError(f"{path}: the mesh has no vertex colours (expected 'v x y z r g b' lines)")
    colors = np.where(np.isnan(colors), 0.5, colors)
    faces = np.array(faces, np.int64).reshape(-1, 3)
    faces = np.where(faces < 0, faces + len(vertices), faces - 1)  # OBJ: 1-based, negative = relative
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise CaptureError(f"{path}: a face refers to a vertex outside 1..{len(vertices)}")
    return ColoredMesh(vertices, np.clip(colors, 0.0, 1.0), faces)


def item_gender(item: str | Path) -> str:
    """'female' or 'male' from a raw item's top folder (``results_..._F`` / ``_M``)."""
    for part in (Path(item), *Path(item).parents):
        match = _ITEM_PATTERN.match(part.name)
        if match:
            return {"F": "female", "M": "male"}[match["gender"]]
    raise CaptureError(f"{item}: not inside a THUman item folder (results_<...>_F or _M)")


@dataclass(frozen=True)
class ThumanRender:
    """One ``render_128`` view: image (128, 128, 3) float32 RGB on black, mask (128, 128) float32 in [0, 1],
    pose_to_camera and pose_to_world (24, 4, 4), K (3, 3) (pixel centres at integers), mesh and view indices."""

    image: np.ndarray
    mask: np.ndarray
    pose_to_camera: np.ndarray
    pose_to_world: np.ndarray
    K: np.ndarray
    mesh: int
    view: int


def load_array(path: Path, shape: tuple[int, ...]) -> np.ndarray:
    """A plain (never pickled) finite ``.npy`` array of ``shape``, as float64.

    Raises:
        CaptureError: the file is missing, pickled or unreadable, of another shape, or holds NaN / inf.
    """
    if not path.is_file():
        raise CaptureError(f"{path}: missing")
    try:
        array = load_npy(path)
    except ValueError as err:
        raise CaptureError(f"{path}: not a plain .npy array ({err})") from err
    if array.shape != shape:
        raise CaptureError(f"{path}: shape {array.shape}, expected {shape}")
    if not np.isfinite(array).all():
        raise CaptureError(f"{path}: holds NaN or inf")
    return array.astype(np.float64)


def read_render(
    color_dir: str | Path,
    index: int,
    renders_per_mesh: int,
    size: int = RENDER_SIZE,
    n_parts: int = 24,
    K: np.ndarray = THUMAN_K,
) -> ThumanRender:
    """Read render ``index`` of a ``render_128/color`` folder (BGRA PNG, alpha = mask; module docstring).

    ``size``, ``n_parts`` and ``K``: the same layout for other objects (the rigid-object set, ``docs/formats.md``:
    ``render_200``, one part, its own intrinsics).

    Raises:
        CaptureError: a file is missing or unreadable, or the image is not size x size with an alpha channel.
    """
    color_dir = Path(color_dir)
    image_path = color_dir / f"color_{index:08d}.png"
    bgra = read_image(image_path, cv2.IMREAD_UNCHANGED)
    if bgra.shape != (size, size, 4):
        raise CaptureError(f"{image_path}: shape {bgra.shape}, expected a {size}x{size} BGRA image (alpha = mask)")
    scale = 65535.0 if bgra.dtype == np.uint16 else 255.0
    rgba = cv2.cvtColor(bgra, cv2.COLOR_BGRA2RGBA).astype(np.float32) / scale
    mask = rgba[..., 3]
    return ThumanRender(
        image=rgba[..., :3] * (mask[..., None] > 0),
        mask=mask,
        pose_to_camera=load_array(color_dir / f"pose_to_camera_{index:08d}.npy", (n_parts, 4, 4)),
        pose_to_world=load_array(color_dir / f"pose_to_world_{index:08d}.npy", (n_parts, 4, 4)),
        K=np.array(K, dtype=np.float64),
        mesh=index // renders_per_mesh,
        view=index % renders_per_mesh,
    )


def count_renders(color_dir: str | Path) -> int:
    """Number of consecutive ``color_%08d.png`` renders from 0 (a gap ends the count)."""
    color_dir = Path(color_dir)
    if not color_dir.is_dir():
        raise CaptureError(f"{color_dir}: no such render_128/color folder")
    present = {int(p.stem.split("_")[1]) for p in color_dir.glob("color_*.png") if p.stem.split("_")[1].isdigit()}
    count = 0
    while count in present:
        count += 1
    return count
