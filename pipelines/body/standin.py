"""Procedural SMPL-format stand-in body model (the embedded default; the licensed SMPL files cannot ship).

The surface is seven closed generalised cylinders ("tubes") laid along the SMPL-24 rest skeleton: torso with
neck and head, two legs, two feet and two arms with flat hands. Each tube has a ring of vertices exactly at
every joint it carries, so a uniform average over that ring regresses the joint (``J_regressor`` rows sum to
1). The tubes are joined into one genus-0 surface by hidden connected sums (a triangular prism between one
face of the child tube lying inside the parent and one face of the parent lying inside the child), which gives
exactly SMPL's V = 6890 vertices and F = 2V - 4 = 13776 faces. Vertices are permuted so that smplx's
vertex-picked extra joints (nose, eyes, ears, toes, heels, fingertips) land on the matching body points.

Skinning weights are per ring, blended smoothly (smoothstep) across every joint; 10 shape directions change
height, girth, limb lengths, widths and head size; pose correctives bulge the skin at bent joints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import trimesh
from smplx.vertex_ids import vertex_ids as SMPL_VERTEX_IDS

from narf.kinematics import SMPL_PARENTS

N_VERTS, N_FACES, N_BETAS = 6890, 13776, 10

#: Rest joints close to SMPL's neutral body (metres, y up, +x = body left, +z = forward).
REST_JOINTS = np.array(
    [
        [-0.0018, -0.2233, 0.0282],
        [0.0695, -0.3141, 0.0239],
        [-0.0677, -0.3147, 0.0214],
        [-0.0025, -0.1033, 0.0120],
        [0.1040, -0.6710, 0.0156],
        [-0.1060, -0.6740, 0.0146],
        [0.0050, 0.0302, 0.0290],
        [0.0870, -1.0770, -0.0298],
        [-0.0880, -1.0820, -0.0300],
        [0.0020, 0.0880, 0.0310],
        [0.1200, -1.1370, 0.0900],
        [-0.1180, -1.1400, 0.0950],
        [-0.0010, 0.2950, -0.0040],
        [0.0770, 0.2040, -0.0050],
        [-0.0790, 0.2030, -0.0090],
        [0.0050, 0.3600, 0.0490],
        [0.1700, 0.2300, -0.0150],
        [-0.1700, 0.2300, -0.0150],
        [0.4300, 0.2100, -0.0300],
        [-0.4300, 0.2100, -0.0300],
        [0.6800, 0.2200, -0.0250],
        [-0.6800, 0.2200, -0.0250],
        [0.7600, 0.2100, -0.0350],
        [-0.7600, 0.2100, -0.0350],
    ]
)


@dataclass(frozen=True)
class TubeSpec:
    """One generalised cylinder: a polyline of nodes with a cross-section profile.

    nodes: positions (K, 3); node_joints: SMPL joint at each node or -1 (regressed from that node's ring);
    segment_joints: skinning joint of each of the K-1 segments; profile: (fractional node index, half-width
    along ``side``, half-depth along the other axis); side: reference axis of the cross-section.
    """

    name: str
    nodes: np.ndarray
    node_joints: tuple[int, ...]
    segment_joints: tuple[int, ...]
    profile: tuple[tuple[float, float, float], ...]
    side: tuple[float, float, float]
    n_rings: int
    n_segments: int


def _j(i: int) -> list[float]:
    return REST_JOINTS[i].tolist()


def _left_specs() -> list[TubeSpec]:
    torso = TubeSpec(
        "torso",
        np.array([[0.0, -0.40, 0.01], _j(0), _j(3), _j(6), _j(9), _j(12), _j(15), [0.005, 0.60, 0.01]]),
        (-1, 0, 3, 6, 9, 12, 15, -1),
        (0, 0, 3, 6, 9, 12, 15),
        (
            (0.0, 0.06, 0.05),
            (0.3, 0.15, 0.10),
            (1.0, 0.175, 0.115),
            (2.0, 0.15, 0.105),
            (3.0, 0.16, 0.11),
            (4.0, 0.17, 0.115),
            (4.5, 0.185, 0.12),
            (4.8, 0.19, 0.095),
            (4.95, 0.11, 0.07),
            (5.0, 0.06, 0.055),
            (5.6, 0.058, 0.058),
            (6.0, 0.075, 0.09),
            (6.4, 0.085, 0.10),
            (6.75, 0.075, 0.09),
            (7.0, 0.025, 0.03),
        ),
        (1.0, 0.0, 0.0),
        65,
        44,
    )
    leg = TubeSpec(
        "left_leg",
        np.array([[0.065, -0.24, 0.025], _j(1), _j(4), _j(7), [0.087, -1.12, -0.035]]),
        (-1, 1, 4, 7, -1),
        (0, 1, 4, 7),
        (
            (0.0, 0.06, 0.06),
            (0.5, 0.08, 0.085),
            (1.0, 0.085, 0.088),
            (1.3, 0.078, 0.08),
            (1.9, 0.055, 0.056),
            (2.0, 0.052, 0.054),
            (2.3, 0.055, 0.06),
            (2.9, 0.037, 0.04),
            (3.0, 0.036, 0.04),
            (4.0, 0.03, 0.035),
        ),
        (1.0, 0.0, 0.0),
        40,
        24,
    )
    foot = TubeSpec(
        "left_foot",
        np.array([[0.085, -1.12, -0.09], [0.087, -1.12, -0.03], _j(10), [0.125, -1.14, 0.17]]),
        (-1, -1, 10, -1),
        (7, 7, 10),
        ((0.0, 0.03, 0.03), (0.5, 0.04, 0.045), (1.0, 0.045, 0.05), (2.0, 0.05, 0.03), (3.0, 0.02, 0.015)),
        (1.0, 0.0, 0.0),
        14,
        12,
    )
    arm = TubeSpec(
        "left_arm",
        np.array([[0.04, 0.215, -0.005], _j(13), _j(16), _j(18), _j(20), _j(22), [0.85, 0.205, -0.035]]),
        (-1, 13, 16, 18, 20, 22, -1),
        (13, 13, 16, 18, 20, 22),
        (
            (0.0, 0.04, 0.04),
            (1.0, 0.06, 0.06),
            (2.0, 0.058, 0.055),
            (2.4, 0.048, 0.048),
            (3.0, 0.038, 0.04),
            (3.3, 0.04, 0.042),
            (4.0, 0.027, 0.032),
            (4.5, 0.022, 0.045),
            (5.0, 0.016, 0.045),
            (5.6, 0.012, 0.038),
            (6.0, 0.008, 0.01),
        ),
        (0.0, 1.0, 0.0),
        44,
        20,
    )
    return [torso, leg, foot, arm]


_MIRROR_JOINT = (0, 2, 1, 3, 5, 4, 6, 8, 7, 9, 11, 10, 12, 14, 13, 15, 17, 16, 19, 18, 21, 20, 23, 22)


def _mirror(spec: TubeSpec) -> TubeSpec:
    nodes = spec.nodes * np.array([-1.0, 1.0, 1.0])
    swap = [(-1 if j < 0 else _MIRROR_JOINT[j]) for j in spec.node_joints]
    # Mirror the joint positions exactly onto the right-side rest joints where a node carries a joint.
    for k, j in enumerate(swap):
        if j >= 0:
            nodes[k] = REST_JOINTS[j]
    return TubeSpec(
        spec.name.replace("left", "right"),
        nodes,
        tuple(swap),
        tuple(_MIRROR_JOINT[j] for j in spec.segment_joints),
        spec.profile,
        spec.side,
        spec.n_rings,
        spec.n_segments,
    )


def tube_specs() -> list[TubeSpec]:
    """The seven tubes in merge order: torso, left/right leg, left/right foot, left/right arm."""
    torso, leg, foot, arm = _left_specs()
    return [torso, leg, _mirror(leg), foot, _mirror(foot), arm, _mirror(arm)]


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _ring_positions(arc: np.ndarray, n_rings: int) -> np.ndarray:
    """Arc-length positions of the rings: one at every node, the rest spread proportionally to length."""
    seg = np.diff(arc)
    extra = n_rings - len(arc)
    share = seg / seg.sum() * extra
    counts = np.floor(share).astype(int)
    for k in np.argsort(-(share - counts))[: extra - counts.sum()]:
        counts[k] += 1
    out = []
    for k, n in enumerate(counts):
        out.extend(arc[k] + seg[k] * np.arange(n + 1) / (n + 1))
    out.append(arc[-1])
    return np.asarray(out)


@dataclass
class _Tube:
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    weights: np.ndarray  # (V, 24)
    centres: np.ndarray  # (V, 3) spine point of each vertex
    joint_rings: dict  # joint -> vertex indices of its ring
    ring_of: np.ndarray  # (V,) fractional node index of each vertex


def _build_tube(spec: TubeSpec) -> _Tube:
    nodes = spec.nodes
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(nodes, axis=0), axis=1))])
    rings_t = _ring_positions(arc, spec.n_rings)
    frac = np.interp(rings_t, arc, np.arange(len(arc)))
    centres = np.stack([np.interp(rings_t, arc, nodes[:, d]) for d in range(3)], axis=1)
    seg_dirs = np.diff(nodes, axis=0)
    seg_dirs /= np.linalg.norm(seg_dirs, axis=1, keepdims=True)
    node_dirs = np.concatenate([seg_dirs[:1], seg_dirs[:-1] + seg_dirs[1:], seg_dirs[-1:]])
    node_dirs /= np.linalg.norm(node_dirs, axis=1, keepdims=True)
    tangents = np.stack([np.interp(frac, np.arange(len(arc)), node_dirs[:, d]) for d in range(3)], axis=1)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    side = np.asarray(spec.side, dtype=float)
    side = side - (tangents @ side)[:, None] * tangents
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    depth = np.cross(tangents, side)
    knots = np.asarray(spec.profile)
    knot_pos = knots[:, 0]
    idx = np.clip(np.searchsorted(knot_pos, frac, side="right") - 1, 0, len(knot_pos) - 2)
    u = _smoothstep((frac - knot_pos[idx]) / (knot_pos[idx + 1] - knot_pos[idx]))
    half_w = knots[idx, 1] + u * (knots[idx + 1, 1] - knots[idx, 1])
    half_d = knots[idx, 2] + u * (knots[idx + 1, 2] - knots[idx, 2])
    n_rings, n_seg = len(rings_t), spec.n_segments
    phi = 2 * np.pi * np.arange(n_seg) / n_seg
    ring_pts = (
        centres[:, None]
        + half_w[:, None, None] * np.cos(phi)[None, :, None] * side[:, None]
        + half_d[:, None, None] * np.sin(phi)[None, :, None] * depth[:, None]
    )
    cap = 0.35 * np.minimum(half_w[[0, -1]], half_d[[0, -1]])
    poles = np.stack([centres[0] - cap[0] * tangents[0], centres[-1] + cap[1] * tangents[-1]])
    vertices = np.concatenate([ring_pts.reshape(-1, 3), poles])
    faces = []
    grid = np.arange(n_rings * n_seg).reshape(n_rings, n_seg)
    nxt = np.roll(grid, -1, axis=1)
    for r in range(n_rings - 1):
        a, b, c, d = grid[r], nxt[r], grid[r + 1], nxt[r + 1]
        faces.append(np.stack([a, c, b], 1))
        faces.append(np.stack([b, c, d], 1))
    first, last = n_rings * n_seg, n_rings * n_seg + 1
    faces.append(np.stack([np.full(n_seg, first), grid[0], nxt[0]], 1))
    faces.append(np.stack([np.full(n_seg, last), nxt[-1], grid[-1]], 1))
    faces = np.concatenate(faces)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if mesh.volume < 0:
        faces = faces[:, ::-1].copy()
    ring_weights = _ring_weights(spec, frac)
    weights = np.concatenate([np.repeat(ring_weights, n_seg, axis=0), ring_weights[[0, -1]]])
    vert_centres = np.concatenate([np.repeat(centres, n_seg, axis=0), centres[[0, -1]]])
    vert_frac = np.concatenate([np.repeat(frac, n_seg), frac[[0, -1]]])
    joint_rings = {}
    for k, joint in enumerate(spec.node_joints):
        if joint >= 0:
            r = int(np.argmin(np.abs(frac - k)))
            joint_rings[joint] = grid[r]
    return _Tube(vertices, faces, weights, vert_centres, joint_rings, vert_frac)


def _ring_weights(spec: TubeSpec, frac: np.ndarray) -> np.ndarray:
    """Per-ring skinning weights: segment joints, blended by smoothstep within 35% of each segment at nodes."""
    n_nodes = len(spec.nodes)
    weights = np.zeros((len(frac), 24))
    seg = np.clip(np.floor(frac).astype(int), 0, n_nodes - 2)
    weights[np.arange(len(frac)), np.array(spec.segment_joints)[seg]] = 1.0
    for k in range(1, n_nodes - 1):
        before, after = spec.segment_joints[k - 1], spec.segment_joints[k]
        if before == after:
            continue
        near = np.abs(frac - k) < 0.35
        s = _smoothstep((frac[near] - (k - 0.35)) / 0.7)
        weights[near] = 0.0
        weights[near, before] += 1 - s
        weights[near, after] += s
    return weights


#: (child tube, parent tube) pairs joined by a hidden connected sum.
_JOINS = (
    ("left_leg", "torso"),
    ("right_leg", "torso"),
    ("left_foot", "left_leg"),
    ("right_foot", "right_leg"),
    ("left_arm", "torso"),
    ("right_arm", "torso"),
)
#: Where smplx's vertex-picked extra joints should sit on the body (left side; right side mirrored).
_EXTRA_TARGETS = {
    "nose": (0.0, 0.42, 0.16),
    "leye": (0.035, 0.46, 0.12),
    "lear": (0.09, 0.44, 0.02),
    "LBigToe": (0.105, -1.14, 0.19),
    "LSmallToe": (0.15, -1.14, 0.16),
    "LHeel": (0.085, -1.16, -0.12),
    "lthumb": (0.78, 0.21, 0.06),
    "lindex": (0.85, 0.205, 0.04),
    "lmiddle": (0.86, 0.205, 0.01),
    "lring": (0.85, 0.205, -0.02),
    "lpinky": (0.83, 0.205, -0.05),
}


def _connected_sum(faces: np.ndarray, vertices: np.ndarray, child: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """Join two closed components by a prism between a child face inside the parent and a parent face inside
    the child (both hidden). ``child`` / ``parent`` are boolean face masks. Returns the new faces."""
    centroids = vertices[faces].mean(axis=1)
    parent_mesh = trimesh.Trimesh(vertices, faces[parent], process=False)
    child_mesh = trimesh.Trimesh(vertices, faces[child], process=False)
    child_ids = np.flatnonzero(child)[parent_mesh.contains(centroids[child])]
    parent_ids = np.flatnonzero(parent)[child_mesh.contains(centroids[parent])]
    if len(child_ids) == 0 or len(parent_ids) == 0:
        raise RuntimeError("stand-in body: tubes do not overlap where they should be joined")
    dists = np.linalg.norm(centroids[child_ids][:, None] - centroids[parent_ids][None], axis=-1)
    ci, pi = np.unravel_index(np.argmin(dists), dists.shape)
    a, b = faces[child_ids[ci]], faces[parent_ids[pi]]
    b_rev = b[[0, 2, 1]]
    best = min(range(3), key=lambda s: np.linalg.norm(vertices[a] - vertices[np.roll(b_rev, s)], axis=1).sum())
    m = np.roll(b_rev, best)
    walls = []
    for i in range(3):
        j = (i + 1) % 3
        walls += [[a[i], a[j], m[j]], [a[i], m[j], m[i]]]
    keep = np.ones(len(faces), bool)
    keep[[child_ids[ci], parent_ids[pi]]] = False
    return np.concatenate([faces[keep], np.asarray(walls, dtype=faces.dtype)])


def _merge_tubes(specs: list[TubeSpec]) -> dict:
    tubes = [_build_tube(s) for s in specs]
    offsets = np.cumsum([0] + [len(t.vertices) for t in tubes])
    vertices = np.concatenate([t.vertices for t in tubes])
    face_tube = np.concatenate([np.full(len(t.faces), k) for k, t in enumerate(tubes)])
    faces = np.concatenate([t.faces + offsets[k] for k, t in enumerate(tubes)])
    names = [s.name for s in specs]
    for child, parent in _JOINS:
        vert_tube = np.searchsorted(offsets, np.arange(len(vertices)), side="right") - 1
        face_tube = vert_tube[faces[:, 0]]
        faces = _connected_sum(faces, vertices, face_tube == names.index(child), face_tube == names.index(parent))
    regressor = np.zeros((24, len(vertices)))
    for k, tube in enumerate(tubes):
        for joint, ring in tube.joint_rings.items():
            regressor[joint, ring + offsets[k]] = 1.0 / len(ring)
    return {
        "vertices": vertices,
        "faces": faces,
        "regressor": regressor,
        "weights": np.concatenate([t.weights for t in tubes]),
        "centres": np.concatenate([t.centres for t in tubes]),
        "tube": np.searchsorted(offsets, np.arange(len(vertices)), side="right") - 1,
        "names": names,
    }


def _extra_vertex_permutation(vertices: np.ndarray) -> np.ndarray:
    """Permutation ``perm`` (new index -> old index) placing smplx's extra-joint vertex ids on body points."""
    wanted = {}
    for name, target in _EXTRA_TARGETS.items():
        wanted[name] = np.asarray(target)
        mirror = {"leye": "reye", "lear": "rear"}.get(name) or (
            name.replace("L", "R", 1) if name[0] == "L" else "r" + name[1:] if name[0] == "l" else None
        )
        if mirror and mirror != name:
            wanted[mirror] = np.asarray(target) * np.array([-1.0, 1.0, 1.0])
    perm = -np.ones(len(vertices), dtype=np.int64)
    taken = np.zeros(len(vertices), bool)
    for name, target in wanted.items():
        order = np.argsort(np.linalg.norm(vertices - target, axis=1))
        old = order[~taken[order]][0]
        perm[SMPL_VERTEX_IDS["smplh"][name]] = old
        taken[old] = True
    perm[perm < 0] = np.flatnonzero(~taken)
    return perm


def _shape_directions(v: np.ndarray, centres: np.ndarray, tube: np.ndarray, names: list[str]) -> np.ndarray:
    """Ten smooth displacement fields (V, 3, 10), roughly one standard deviation each."""
    name = np.asarray(names)[tube]
    radial = v - centres
    is_torso, is_arm = name == "torso", np.char.find(name, "arm") >= 0
    is_leg = (np.char.find(name, "leg") >= 0) | (np.char.find(name, "foot") >= 0)
    side = np.sign(v[:, 0])
    head = is_torso & (v[:, 1] > 0.32)
    dirs = np.zeros((len(v), 3, N_BETAS))
    dirs[:, :, 0] = 0.05 * v  # overall height / scale
    dirs[:, :, 1] = radial * np.where(is_torso & ~head, 0.12, np.where(head, 0.0, 0.07))[:, None]  # girth
    leg_frac = np.clip((REST_JOINTS[1, 1] - v[:, 1]) / (REST_JOINTS[1, 1] - REST_JOINTS[7, 1]), 0, 1)
    dirs[:, 1, 2] = -0.045 * leg_frac * is_leg  # leg length
    arm_frac = np.clip((np.abs(v[:, 0]) - 0.17) / (0.68 - 0.17), 0, 1)
    dirs[:, 0, 3] = 0.035 * side * arm_frac * is_arm  # arm length
    upper = _smoothstep((v[:, 1] - 0.05) / 0.15) * is_torso * ~head
    dirs[:, 0, 4] = 0.08 * radial[:, 0] * upper + 0.015 * side * is_arm  # shoulder width
    hips = np.exp(-(((v[:, 1] + 0.25) / 0.12) ** 2)) * is_torso
    dirs[:, 0, 5] = 0.08 * radial[:, 0] * hips + 0.012 * side * is_leg  # hip width
    dirs[:, 1, 6] = 0.025 * (_smoothstep((v[:, 1] + 0.1) / 0.4) * is_torso + is_arm)  # torso length
    head_w = _smoothstep((v[:, 1] - 0.32) / 0.06) * is_torso
    dirs[:, :, 7] = 0.06 * (v - np.array([0.0, 0.46, 0.02])) * head_w[:, None]  # head size
    belly = np.exp(-((v[:, 1] / 0.18) ** 2)) * is_torso
    dirs[:, 2, 8] = 0.15 * radial[:, 2] * belly  # belly / chest depth
    dirs[:, :, 9] = 0.10 * radial * (is_arm | is_leg)[:, None]  # limb thickness
    return dirs


def _pose_directions(v: np.ndarray, centres: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Pose correctives (V, 3, 207): skin bulges by 12 mm (1 - cos theta) where the weights blend at joint j."""
    radial = v - centres
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
    dirs = np.zeros((len(v), 3, 207))
    for j in range(1, 24):
        bulge = 4 * weights[:, j] * (1 - weights[:, j])
        for d in (0, 4, 8):  # the diagonal of (R_j - I) sums to -(2 - 2 cos theta)
            dirs[:, :, 9 * (j - 1) + d] = -0.006 * bulge[:, None] * radial
    return dirs


def build_standin_model() -> dict:
    """Generate the stand-in body as an SMPL model dict (every key smplx and smpl_webuser read). Deterministic."""
    merged = _merge_tubes(tube_specs())
    perm = _extra_vertex_permutation(merged["vertices"])
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(len(perm))
    v = merged["vertices"][perm]
    centres, tube, weights = merged["centres"][perm], merged["tube"][perm], merged["weights"][perm]
    faces = inverse[merged["faces"]].astype(np.uint32)
    regressor = merged["regressor"][:, perm]
    if v.shape != (N_VERTS, 3) or faces.shape != (N_FACES, 3):
        raise RuntimeError(f"stand-in body has {v.shape[0]} vertices / {faces.shape[0]} faces, expected SMPL's")
    kintree = np.stack([np.array(SMPL_PARENTS, dtype=np.int64), np.arange(24, dtype=np.int64)])
    kintree[0, 0] = 4294967295
    j_regressor = scipy.sparse.csc_matrix(regressor)
    return {
        "v_template": v,
        "f": faces,
        "weights": weights,
        "J_regressor": j_regressor,
        "J": j_regressor @ v,
        "kintree_table": kintree,
        "shapedirs": _shape_directions(v, centres, tube, merged["names"]),
        "posedirs": _pose_directions(v, centres, weights),
        "bs_style": "lbs",
        "bs_type": "lrotmin",
    }
