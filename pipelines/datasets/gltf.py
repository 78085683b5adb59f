"""A skinned, animated glTF 2.0 binary (``.glb``) writer: one mesh, one skin, one animation (docs/formats.md §10).

The layout (docs/formats.md §10, which restates the rules of glTF 2.0 that it relies on):

* node ``j`` is joint ``j`` (its name, its children), holding the joint's transform in its parent's frame at the
  bind pose (``translation``, ``rotation``); node ``J`` holds the mesh and the skin; the scene's roots are the root
  joint and the mesh node;
* the skin's ``inverseBindMatrices`` are ``inv(world_from_joint)`` at the bind pose, so a vertex with weights w_j
  moves to ``sum_j w_j G_j(t) inv(G_j(bind)) x`` (linear blend skinning) with G_j the joint's global transform;
* the mesh has ``POSITION``, ``NORMAL``, ``COLOR_0`` (linear RGB: the fitted colours are sRGB and converted),
  ``JOINTS_0`` (unsigned short) and ``WEIGHTS_0`` (float, rows summing to one), an unlit material
  (``KHR_materials_unlit``, optional for readers: the colours are the radiance the field renders);
* the animation samples every joint's local ``rotation`` (unit quaternions x, y, z, w, signs kept continuous) and
  ``translation`` at ``times`` with ``LINEAR`` interpolation.

All matrices are row-major numpy (glTF stores column-major: transposed on write). Pure numpy and json.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

FLOAT, UNSIGNED_SHORT, UNSIGNED_INT = 5126, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
_COMPONENTS = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}


@dataclass
class Skeleton:
    """names (J,); parents (J,) with -1 for the root, every parent before its children; bind (J, 4, 4) the joints'
    global transforms at the bind pose (rotation, origin at the joint)."""

    names: tuple[str, ...]
    parents: tuple[int, ...]
    bind: np.ndarray


@dataclass
class SkinnedMesh:
    """vertices (V, 3) and normals (V, 3) at the bind pose; faces (F, 3) counter-clockwise from outside; colours
    (V, 3) sRGB in [0, 1]; joints (V, 4) int and weights (V, 4) the four influences of each vertex."""

    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    colours: np.ndarray
    joints: np.ndarray
    weights: np.ndarray


@dataclass
class Animation:
    """times (T,) seconds, increasing; world_from_joint (T, J, 4, 4) the joints' global transforms per frame."""

    times: np.ndarray
    world_from_joint: np.ndarray


def local_transforms(world_from_joint: np.ndarray, parents) -> np.ndarray:
    """(..., J, 4, 4) global joint transforms -> transforms in the parent's frame: ``inv(G_parent) G_j``."""
    local = world_from_joint.copy()
    for j, parent in enumerate(parents):
        if parent >= 0:
            local[..., j, :, :] = np.linalg.inv(world_from_joint[..., parent, :, :]) @ world_from_joint[..., j, :, :]
    return local


def continuous_quaternions(rotations: np.ndarray) -> np.ndarray:
    """(T, J, 3, 3) rotations -> (T, J, 4) quaternions (x, y, z, w), each flipped to the sign nearest the previous
    frame's (q and -q are the same rotation; LINEAR interpolation between opposite signs takes the long way)."""
    quats = Rotation.from_matrix(rotations.reshape(-1, 3, 3)).as_quat().reshape(*rotations.shape[:-2], 4)
    for t in range(1, len(quats)):
        flip = np.einsum("jk,jk->j", quats[t], quats[t - 1]) < 0
        quats[t, flip] *= -1
    return quats


def srgb_to_linear(colours: np.ndarray) -> np.ndarray:
    """sRGB to linear (docs/formats.md §10): c / 12.92 below 0.04045, ((c + 0.055) / 1.055) ** 2.4 above."""
    c = np.clip(colours, 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


class _Buffer:
    """The binary chunk and the accessors pointing into it."""

    def __init__(self):
        self.data, self.views, self.accessors = bytearray(), [], []

    def add(self, array: np.ndarray, kind: str, component: int, target: int | None = None, bounds=False) -> int:
        """Append ``array`` (N rows of ``kind``) as a buffer view and an accessor; returns the accessor's index."""
        dtype = {FLOAT: "<f4", UNSIGNED_SHORT: "<u2", UNSIGNED_INT: "<u4"}[component]
        flat = np.ascontiguousarray(array, dtype=dtype)
        self.data.extend(b"\0" * (-len(self.data) % 4))  # every view starts 4-byte aligned
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": flat.nbytes}
        if target is not None:
            view["target"] = target
        self.data.extend(flat.tobytes())
        self.views.append(view)
        count = flat.shape[0]
        accessor = {"bufferView": len(self.views) - 1, "componentType": component, "count": count, "type": kind}
        if bounds:  # required for POSITION and animation inputs
            rows = flat.reshape(count, _COMPONENTS[kind])
            accessor["min"], accessor["max"] = rows.min(0).tolist(), rows.max(0).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def _trs(matrix: np.ndarray) -> dict:
    """A rigid 4x4 as glTF node ``translation`` and ``rotation`` (x, y, z, w)."""
    quat = Rotation.from_matrix(matrix[:3, :3]).as_quat()  # unit length
    return {"translation": matrix[:3, 3].tolist(), "rotation": quat.tolist()}


def _animation(buffer: _Buffer, skeleton: Skeleton, animation: Animation) -> dict:
    local = local_transforms(animation.world_from_joint, skeleton.parents)
    times = buffer.add(np.asarray(animation.times), "SCALAR", FLOAT, bounds=True)
    quats = continuous_quaternions(local[..., :3, :3])
    samplers, channels = [], []
    for j in range(len(skeleton.names)):
        for path, values, kind in (("rotation", quats[:, j], "VEC4"), ("translation", local[:, j, :3, 3], "VEC3")):
            samplers.append({"input": times, "output": buffer.add(values, kind, FLOAT), "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": j, "path": path}})
    return {"name": "motion", "samplers": samplers, "channels": channels}


def skinned_glb(mesh: SkinnedMesh, skeleton: Skeleton, animation: Animation | None = None, name="avatar") -> bytes:
    """The glb bytes of a skinned mesh (module docstring)."""
    n_joints = len(skeleton.names)
    if len(skeleton.parents) != n_joints or skeleton.bind.shape != (n_joints, 4, 4):
        raise ValueError(f"skeleton: {n_joints} names, {len(skeleton.parents)} parents, bind {skeleton.bind.shape}")
    if any(not -1 <= p < j for j, p in enumerate(skeleton.parents)) or skeleton.parents[0] != -1:
        raise ValueError("skeleton: joint 0 must be the root and every parent must come before its children")
    buffer = _Buffer()
    attributes = {
        "POSITION": buffer.add(mesh.vertices, "VEC3", FLOAT, ARRAY_BUFFER, bounds=True),
        "NORMAL": buffer.add(mesh.normals, "VEC3", FLOAT, ARRAY_BUFFER),
        "COLOR_0": buffer.add(srgb_to_linear(mesh.colours), "VEC3", FLOAT, ARRAY_BUFFER),
        "JOINTS_0": buffer.add(mesh.joints, "VEC4", UNSIGNED_SHORT, ARRAY_BUFFER),
        "WEIGHTS_0": buffer.add(mesh.weights, "VEC4", FLOAT, ARRAY_BUFFER),
    }
    indices = buffer.add(mesh.faces.reshape(-1), "SCALAR", UNSIGNED_INT, ELEMENT_ARRAY_BUFFER)
    inverse_bind = np.linalg.inv(skeleton.bind).transpose(0, 2, 1)  # column-major
    skin = {
        "joints": list(range(n_joints)),
        "skeleton": 0,
        "inverseBindMatrices": buffer.add(inverse_bind, "MAT4", FLOAT),
    }
    local = local_transforms(skeleton.bind, skeleton.parents)
    nodes = [{"name": skeleton.names[j], **_trs(local[j])} for j in range(n_joints)]
    for j, parent in enumerate(skeleton.parents):
        if parent >= 0:
            nodes[parent].setdefault("children", []).append(j)
    nodes.append({"name": name, "mesh": 0, "skin": 0})
    document = {
        "asset": {"version": "2.0", "generator": "narf-avatar narf-export-mesh --rigged"},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{"name": name, "nodes": [0, n_joints]}],
        "nodes": nodes,
        "meshes": [{"name": name, "primitives": [{"attributes": attributes, "indices": indices, "material": 0}]}],
        "materials": [
            {
                "name": "fitted colours",
                "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0, "roughnessFactor": 1},
                "extensions": {"KHR_materials_unlit": {}},
            }
        ],
        "skins": [{"name": "skeleton", **skin}],
    }
    if animation is not None:
        document["animations"] = [_animation(buffer, skeleton, animation)]
    buffer.data.extend(b"\0" * (-len(buffer.data) % 4))
    document.update(bufferViews=buffer.views, accessors=buffer.accessors, buffers=[{"byteLength": len(buffer.data)}])
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(buffer.data)
    header = struct.pack("<4sII", b"glTF", 2, total)
    return (
        header
        + struct.pack("<I4s", len(text), b"JSON")
        + text
        + struct.pack("<I4s", len(buffer.data), b"BIN\0")
        + bytes(buffer.data)
    )
