"""A ZJU-MoCap-layout capture on disk: frames, cameras, SMPL fits and evaluation protocols.

``ZjuCapture(root).load_frame(f, c)`` returns a :class:`pipelines.zju_mocap.Frame` processed in the Neural Body
order. Protocols (docs/formats.md §1.8) list the (frame, camera) pairs of each split.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from pipelines.datasets.camera import resized_mask
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.images import read_image
from pipelines.datasets.safe_pickle import load_npy
from pipelines.datasets.zju_mocap import (
    Frame,
    SmplParams,
    boundary_band,
    param_index_from_image,
    read_annots,
    read_params,
)

MASK_SOURCES = ("cihp", "mask", "union")
#: Neural Body frame ranges per subject id: (train begin, n train, novel-pose begin, n novel).
NEURALBODY_FRAMES = {
    313: (0, 60, 60, 1000),
    315: (0, 400, 400, 1000),
    377: (0, 300, 300, 317),
    386: (0, 300, 300, 346),
    387: (0, 300, 300, 354),
    390: (700, 300, 0, 700),
    392: (0, 300, 300, 256),
    393: (0, 300, 300, 358),
    394: (0, 300, 300, 559),
}
SPLITS = (
    "train",
    "same_pose_same_view",
    "same_pose_novel_view",
    "novel_pose_same_view",
    "novel_pose_novel_view",
    "novel_pose",
    "novel_view",
)


@dataclass(frozen=True)
class Protocol:
    """Which frames and views train and test.

    Attributes:
        name: ``neuralbody`` or ``narf``.
        train_views / test_views: camera indices.
        train_frames / novel_frames: frame indices (training poses, held-out poses).
        interval: evaluation uses every ``interval``-th frame of a range (30; less for short captures).
        excluded: (frame, camera) views that neither train nor test (a prepared capture's views where the person
            was not found or was somebody else, docs/formats.md §1.8).
    """

    name: str
    train_views: tuple[int, ...]
    test_views: tuple[int, ...]
    train_frames: tuple[int, ...]
    novel_frames: tuple[int, ...]
    interval: int = 30
    excluded: frozenset = frozenset()

    def split(self, name: str) -> list[tuple[int, int]]:
        """(frame, camera) pairs of a split. ``novel_pose`` = novel poses x test views (Neural Body);
        ``novel_view`` = training poses x test views; ``train`` = every training frame x training view."""
        if name not in SPLITS:
            raise ValueError(f"unknown split '{name}'; choose from {', '.join(SPLITS)}")
        if name == "train":
            return self.usable(self.train_frames, self.train_views)
        alias = {"novel_pose": "novel_pose_novel_view", "novel_view": "same_pose_novel_view"}
        pose, view = alias.get(name, name).split("_pose_")
        frames = (self.train_frames if pose == "same" else self.novel_frames)[:: self.interval]
        views = self.train_views if view == "same_view" else self.test_views
        return self.usable(frames, views)

    def usable(self, frames, views) -> list[tuple[int, int]]:
        """(frame, camera) pairs of ``frames`` x ``views`` that are not excluded."""
        return [(f, c) for f in frames for c in views if (f, c) not in self.excluded]


def make_protocol(name: str, n_frames: int, n_cameras: int, subject_id: int | None = None) -> Protocol:
    """Neural Body protocol (training views 0, 6, 12, 18; per-subject frame ranges) or the NARF supplement's
    (first 90 % of frames train, last 10 % novel pose, same views)."""
    train_views = tuple(v for v in (0, 6, 12, 18) if v < n_cameras)
    if not train_views:
        raise CaptureError(f"a protocol needs at least one camera, the capture has {n_cameras}")
    test_views = tuple(v for v in range(n_cameras) if v not in train_views)
    if name == "neuralbody" and subject_id in NEURALBODY_FRAMES:
        begin, n_train, novel_begin, n_novel = NEURALBODY_FRAMES[subject_id]
        train = range(begin, min(begin + n_train, n_frames))
        novel = range(novel_begin, min(novel_begin + n_novel, n_frames))
    elif name in ("neuralbody", "narf"):
        n_train = max(1, int(round(0.9 * n_frames)))
        train, novel = range(0, n_train), range(n_train, n_frames)
    else:
        raise ValueError(f"unknown protocol '{name}'; choose neuralbody or narf")
    # Every 30th frame, as the protocols; shorter captures keep at least ~5 evaluation frames per range.
    interval = 30 if len(novel) >= 150 else max(1, len(novel) // 5)
    return Protocol(name, train_views, test_views, tuple(train), tuple(novel), interval)


def _indices(path: Path, data: dict, key: str, count: int) -> tuple[int, ...]:
    values = data.get(key)
    if not isinstance(values, list) or not all(isinstance(v, int) and 0 <= v < count for v in values):
        raise CaptureError(f"{path}: '{key}' must be a list of whole numbers in [0, {count})")
    return tuple(values)


def read_splits(path: Path, n_frames: int, n_cameras: int) -> Protocol:
    """A capture's own splits (docs/formats.md §1.8): train/novel frames, train/test views, excluded views."""
    import json

    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CaptureError(f"{path}: not a splits file ({err})") from None
    if not isinstance(data, dict):
        raise CaptureError(f"{path}: expected a JSON object")
    frames = {k: _indices(path, data, k, n_frames) for k in ("train_frames", "novel_frames")}
    views = {k: _indices(path, data, k, n_cameras) for k in ("train_views", "test_views")}
    if not frames["train_frames"] or not views["train_views"]:
        raise CaptureError(f"{path}: no training frame or no training view")
    excluded = data.get("excluded", [])
    if not isinstance(excluded, list) or not all(
        isinstance(e, list) and len(e) == 2 and all(isinstance(i, int) for i in e) for e in excluded
    ):
        raise CaptureError(f"{path}: 'excluded' must be a list of [frame, camera] pairs")
    novel = frames["novel_frames"]
    interval = 30 if len(novel) >= 150 else max(1, len(novel) // 5)
    return Protocol(
        "capture",
        views["train_views"],
        views["test_views"],
        frames["train_frames"],
        novel,
        interval,
        frozenset(map(tuple, excluded)),
    )


class ZjuCapture:
    """A ZJU-MoCap-layout subject folder.

    Args:
        root: the ``CoreView_*`` (or synthetic) folder holding ``annots.npy``.
        ratio: resize ratio (Neural Body uses 0.5 on 1024^2 images).
        mask_source: ``cihp`` (mask_cihp != 0), ``mask`` (binary) or ``union``.
        new_params: read ``new_params/`` (with pose blend shapes) instead of ``params/``.
        white_background: composite onto white instead of black.
    """

    def __init__(
        self,
        root: str | Path,
        ratio: float = 0.5,
        mask_source: str = "cihp",
        new_params: bool = True,
        white_background: bool = False,
    ):
        self.root = Path(root)
        if not (self.root / "annots.npy").is_file():
            raise CaptureError(f"{self.root}: no annots.npy (not a ZJU-MoCap subject folder)")
        if mask_source not in MASK_SOURCES:
            raise ValueError(f"mask_source must be one of {MASK_SOURCES}, got '{mask_source}'")
        if not 0 < ratio <= 1:
            raise ValueError(f"ratio must be in (0, 1], got {ratio}")
        self.ratio, self.mask_source, self.white_background = ratio, mask_source, white_background
        self.params_dir = "new_params" if new_params and (self.root / "new_params").is_dir() else "params"
        self.vertices_dir = self.params_dir.replace("params", "vertices")
        self.cameras, self.ims = read_annots(self.root / "annots.npy")
        for cam in self.cameras:
            if not (self.root / cam.name).is_dir():
                raise CaptureError(f"{self.root / cam.name}: camera folder listed in annots.npy is missing")
        self._frame_of_entry = [param_index_from_image(entry[0]) for entry in self.ims]
        self._maps: dict[int, tuple] = {}

    @property
    def n_frames(self) -> int:
        return len(self.ims)

    @property
    def n_cameras(self) -> int:
        return len(self.cameras)

    @cached_property
    def subject_id(self) -> int | None:
        digits = "".join(ch for ch in self.root.name.split("_")[-1] if ch.isdigit())
        return int(digits) if digits else None

    @cached_property
    def floor(self):
        """The capture's floor (``floor.json``, written by narf-prepare-capture: docs/formats.md §1.10), or None."""
        from pipelines.datasets.floor import read_floor

        path = self.root / "floor.json"
        return read_floor(path) if path.is_file() else None

    @cached_property
    def camera_gains(self) -> np.ndarray | None:
        """(C, 3) each camera's colour gain (``colour.json``: docs/formats.md §1.12), or None where there is none."""
        from pipelines.datasets.camera_colour import read_camera_colour

        path = self.root / "colour.json"
        return read_camera_colour(path, [c.name for c in self.cameras]) if path.is_file() else None

    def surface_displacement(self, n_vertices: int) -> np.ndarray | None:
        """(n_vertices,) each body template vertex's displacement along its normal, metres (``body_surface.npy``,
        written by narf-prepare-capture: docs/formats.md §1.13), or None where there is none."""
        from pipelines.datasets.zju_mocap import BODY_SURFACE, read_body_surface

        path = self.root / BODY_SURFACE
        return read_body_surface(path, n_vertices) if path.is_file() else None

    def person_pixels(self, frame: int, cam: int) -> tuple[np.ndarray, np.ndarray]:
        """The view as recorded: (H, W, 3) uint8 BGR image, not undistorted, and (H, W) bool of the pixels that are
        the person's or of unknown owner (the mask and ``mask_unknown/``)."""
        self._check_frame(frame)
        path = self.root / self.ims[frame][cam]
        bgr = read_image(path)
        mask, _ = self._read_mask(frame, cam, bgr.shape[:2])
        unknown = self._read_unknown(frame, cam, bgr.shape[:2])
        return bgr, mask if unknown is None else mask | unknown

    def protocol(self, name: str = "neuralbody") -> Protocol:
        """The capture's own ``splits.json`` when it has one (written by narf-prepare-capture), else the named
        protocol."""
        if (self.root / "splits.json").is_file():
            return read_splits(self.root / "splits.json", self.n_frames, self.n_cameras)
        return make_protocol(name, self.n_frames, self.n_cameras, self.subject_id)

    def params(self, frame: int) -> SmplParams:
        """SMPL parameters of frame ``frame`` (0-based annots entry)."""
        self._check_frame(frame)
        return read_params(self.root / self.params_dir / f"{self._frame_of_entry[frame][1]}.npy")

    def vertices(self, frame: int) -> np.ndarray:
        """(6890, 3) world vertices of frame ``frame``."""
        self._check_frame(frame)
        path = self.root / self.vertices_dir / f"{self._frame_of_entry[frame][1]}.npy"
        if not path.is_file():
            raise CaptureError(f"{path}: missing")
        verts = load_npy(path)
        if verts.ndim != 2 or verts.shape[1] != 3 or not np.isfinite(verts).all():
            raise CaptureError(f"{path}: expected finite (V, 3) vertices, got shape {verts.shape}")
        return verts.astype(np.float32)

    def _check_frame(self, frame: int) -> None:
        if not 0 <= frame < self.n_frames:
            raise CaptureError(f"{self.root}: frame {frame} out of range (annots lists {self.n_frames} frames)")

    def _read_mask(self, frame: int, cam: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        rel = Path(self.ims[frame][cam]).with_suffix(".png")
        sources = {"cihp": ["mask_cihp"], "mask": ["mask"], "union": ["mask", "mask_cihp"]}[self.mask_source]
        masks, labels = [], np.zeros(shape, np.uint8)
        for folder in sources:
            path = self.root / folder / rel
            raw = read_image(path, cv2.IMREAD_UNCHANGED, "mask")
            raw = raw[..., 0] if raw.ndim == 3 else raw
            if raw.shape != shape:
                raise CaptureError(
                    f"{path}: mask is {raw.shape[1]}x{raw.shape[0]} but the image is {shape[1]}x{shape[0]}"
                )
            masks.append(raw != 0)
            if folder == "mask_cihp":
                labels = raw.astype(np.uint8)
        return np.logical_or.reduce(masks), labels

    def _read_unknown(self, frame: int, cam: int, shape: tuple[int, int]) -> np.ndarray | None:
        """The view's ``mask_unknown/`` image as (H, W) bool (docs/formats.md §1.5), or None where there is none."""
        path = self.root / "mask_unknown" / Path(self.ims[frame][cam]).with_suffix(".png")
        if not path.is_file():
            return None
        raw = read_image(path, cv2.IMREAD_GRAYSCALE, "mask")
        if raw.shape != shape:
            raise CaptureError(f"{path}: mask is {raw.shape[1]}x{raw.shape[0]} but the image is {shape[1]}x{shape[0]}")
        return raw != 0

    def _undistort_maps(self, cam: int) -> tuple:
        """Camera ``cam``'s undistortion maps, computed on first use: fixed-point ones (those ``cv2.undistort``
        builds, for the image) and float ones (for masks and labels, nearest neighbour)."""
        if cam not in self._maps:
            camera = self.cameras[cam]
            size = (camera.width, camera.height)
            build = lambda kind: cv2.initUndistortRectifyMap(camera.K, camera.dist, None, camera.K, size, kind)  # noqa: E731
            self._maps[cam] = (build(cv2.CV_16SC2), build(cv2.CV_32FC1))
        return self._maps[cam]

    def load_frame(self, frame: int, cam: int) -> Frame:
        """Load one view in the Neural Body order (module docstring)."""
        self._check_frame(frame)
        if not 0 <= cam < self.n_cameras:
            raise CaptureError(f"{self.root}: camera {cam} out of range ({self.n_cameras} cameras)")
        path = self.root / self.ims[frame][cam]
        bgr = read_image(path)
        camera = self.cameras[cam]
        if (bgr.shape[1], bgr.shape[0]) != (camera.width, camera.height):
            raise CaptureError(
                f"{path}: image is {bgr.shape[1]}x{bgr.shape[0]}, camera {camera.name} images are "
                f"{camera.width}x{camera.height}"
            )
        image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
        mask, labels = self._read_mask(frame, cam, image.shape[:2])
        unknown = self._read_unknown(frame, cam, image.shape[:2])
        if unknown is not None:
            mask, labels = mask & ~unknown, np.where(unknown, 0, labels).astype(np.uint8)
        if np.any(camera.dist != 0):
            image_maps, maps = self._undistort_maps(cam)
            image = cv2.remap(image, *image_maps, cv2.INTER_LINEAR)  # exactly cv2.undistort, maps computed once
            mask = cv2.remap(mask.astype(np.uint8), *maps, cv2.INTER_NEAREST) > 0
            labels = cv2.remap(labels, *maps, cv2.INTER_NEAREST)
            if unknown is not None:
                unknown = cv2.remap(unknown.astype(np.uint8), *maps, cv2.INTER_NEAREST) > 0
        band = boundary_band(mask)
        if unknown is not None:
            band |= unknown
        seen = camera.undistorted().scaled(self.ratio)  # the camera of the image as returned, its size included
        if self.ratio != 1:
            size = (seen.width, seen.height)
            # each pixel averages the same area of the original as the image's, centred where the camera's rays
            # go (docs/formats.md §0): the mask and the band by resized_mask, the unknown pixels whatever touches
            # it, and they stay in the band; the part labels (a category) are the nearest pixel's
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            mask, band = resized_mask(mask, size), resized_mask(band, size)
            labels = cv2.resize(labels, size, interpolation=cv2.INTER_NEAREST)
            if unknown is not None:
                unknown = cv2.resize(unknown.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0
                band |= unknown
        background = 1.0 if self.white_background else 0.0
        image[~mask & ~band] = background
        if unknown is not None:  # somebody else's colours: compared with nothing, trained on nowhere
            image[unknown] = background
        return Frame(
            frame_index=self._frame_of_entry[frame][0],
            camera_index=cam,
            image=image,
            mask=mask.astype(np.float32),
            band=band,
            labels=labels,
            camera=seen,
            params=self.params(frame),
            image_path=path,
            unknown=unknown,
        )
