"""A rigid-object set in NARF's render layout (``docs/formats.md §8``; written by ``narf-synth --dataset rigid``):
``<root>/<split>/render_<N>/color/color_%08d.png`` (BGRA, alpha = mask), ``pose_to_world_%08d.npy`` and
``pose_to_camera_%08d.npy`` (1, 4, 4) per image, ``<root>/<split>/render_<N>/K.npy`` (3, 3, pixel centres at
integers), and ``<root>/synthetic.json`` with ``object_radius`` (world units; the rigid models' unit s)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from narf.fields.common import PoseBatch
from narf.geometry import se3_log
from pipelines.datasets.camera import Camera
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.thuman import ThumanView, count_renders, load_array, read_render

RIGID_SPLITS = ("train", "test")


@dataclass(frozen=True)
class RigidSet:
    """A rigid-object set: its root, image side, intrinsics (3, 3), object radius and image count per split."""

    root: Path
    size: int
    K: np.ndarray
    radius: float
    counts: dict

    def color_dir(self, split: str) -> Path:
        return self.root / split / f"render_{self.size}" / "color"


def _render_folder(root: Path, split: str) -> Path:
    found = sorted(p for p in (root / split).glob("render_*") if p.is_dir() and p.name[7:].isdigit())
    if len(found) != 1:
        raise CaptureError(f"{root / split}: expected one render_<size> folder, found {len(found)}")
    return found[0]


def _read_K(path: Path) -> np.ndarray:
    K = load_array(path, (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CaptureError(f"{path}: focal lengths must be positive")
    return K


def open_rigid(root: str | Path) -> RigidSet:
    """Check the layout and read the intrinsics, radius and counts (module docstring).

    Raises:
        CaptureError: a folder, ``K.npy`` or the radius is missing or malformed, or the splits differ in size or K.
    """
    root = Path(root)
    marker = root / "synthetic.json"
    try:
        radius = float(json.loads(marker.read_text())["object_radius"])
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise CaptureError(f"{marker}: missing or without a numeric 'object_radius' ({err})") from err
    if not radius > 0:
        raise CaptureError(f"{marker}: object_radius must be positive, got {radius}")
    folders = {split: _render_folder(root, split) for split in RIGID_SPLITS}
    sizes = {int(f.name[7:]) for f in folders.values()}
    Ks = [_read_K(f / "K.npy") for f in folders.values()]
    if len(sizes) != 1 or not np.allclose(Ks[0], Ks[1]):
        raise CaptureError(f"{root}: the train and test splits differ in image size or intrinsics")
    counts = {split: count_renders(f / "color") for split, f in folders.items()}
    for split, count in counts.items():
        if count == 0:
            raise CaptureError(f"{folders[split] / 'color'}: no color_00000000.png")
    return RigidSet(root, sizes.pop(), Ks[0], radius, counts)


def rigid_pose_batch(world_from_object: torch.Tensor, radius: float) -> PoseBatch:
    """Model inputs of a rigid object (one part; paper Eqs. 9-11): l = world_from_object, s = the object radius,
    xi = log([R | t / s]) (the world translation is kept: it is part of the object's pose), no bone lengths.

    Args:
        world_from_object: (B, 4, 4) rigid transforms.
        radius: object radius in world units.

    Returns:
        PoseBatch: world_from_part (B, 1, 4, 4), reach (B,), bone_lengths (B, 0), pose_features (B, 1, 6),
        rest_offsets (B, 1, 3) zeros.
    """
    n = world_from_object.shape[0]
    reach = torch.full((n,), float(radius), dtype=world_from_object.dtype)
    normalised = world_from_object.clone()
    normalised[:, :3, 3] = world_from_object[:, :3, 3] / radius
    pose = se3_log(normalised)[:, None]
    no_bones, no_offsets = world_from_object.new_zeros(n, 0), pose.new_zeros(n, 1, 3)
    return PoseBatch(world_from_object[:, None], reach, no_bones, pose, no_offsets)


def load_rigid_views(rigid: RigidSet, split: str, indices: list[int] | None = None) -> tuple[list, PoseBatch]:
    """Views (image, mask, no boundary band, camera = pose_to_camera pose_to_world^-1) and the PoseBatch of the
    images ``indices`` of ``split`` (default: all)."""
    indices = list(range(rigid.counts[split])) if indices is None else indices
    views, poses = [], []
    for index in indices:
        render = read_render(rigid.color_dir(split), index, 1, size=rigid.size, n_parts=1, K=rigid.K)
        cam_from_world = render.pose_to_camera[0] @ np.linalg.inv(render.pose_to_world[0])
        camera = Camera(f"{split}/{index}", rigid.K, np.zeros(5), cam_from_world, rigid.size, rigid.size)
        views.append(ThumanView(render.image, render.mask, np.zeros(render.mask.shape, bool), camera))
        poses.append(render.pose_to_world[0])
    pose = rigid_pose_batch(torch.as_tensor(np.stack(poses), dtype=torch.float64), rigid.radius)
    return views, pose._map(lambda v: v.to(torch.float32))
