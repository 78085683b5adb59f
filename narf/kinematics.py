"""SMPL-24 kinematic tree, NARF parts, bone lengths and part boxes (docs/model.md §1).

Pure torch: no file I/O. The skinning transforms come from ``smplx.lbs`` (the well-kept reference
implementation); this module turns them into frame-explicit ``world_from_part`` transforms.

Conventions:
    * ``world_from_smpl`` is the dataset's global transform (ZJU ``[R(Rh) | Th]``), left-multiplied onto
      every joint transform.
    * ``world_from_joint[j] = world_from_smpl @ [rot(A_j) | posed J_j]`` where ``A`` are smplx's skinning
      transforms; at rest the rotation is the identity and the origin is the rest joint.
"""

from __future__ import annotations

import torch
from smplx.lbs import batch_rigid_transform, batch_rodrigues

from narf.geometry import check_shape, se3_log

N_JOINTS = 24
N_PARTS = 19
#: SMPL-24 parents (joint order of smplx ``joint_names.py``).
SMPL_PARENTS: tuple[int, ...] = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
JOINT_NAMES: tuple[str, ...] = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
)
#: The joints that have children, in joint order: one NARF part each.
PART_JOINTS: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
#: Parent part of each part (indices into PART_JOINTS).
PART_PARENTS: tuple[int, ...] = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 9, 9, 9, 11, 12, 13, 14, 15, 16)
#: Child joint of each bone whose length enters zeta (every bone but those ending at joints 2, 3, 13, 14).
BONE_CHILDREN: tuple[int, ...] = (1, 4, 5, 6, 7, 8, 9, 10, 11, 12, 15, 16, 17, 18, 19, 20, 21, 22, 23)
#: Part index owning each joint: leaves 10, 11, 15, 22, 23 belong to their parents' parts.
JOINT_TO_PART: tuple[int, ...] = tuple(
    PART_JOINTS.index(j) if j in PART_JOINTS else PART_JOINTS.index(SMPL_PARENTS[j]) for j in range(N_JOINTS)
)


def rigid_from_rotvec_translation(rotvecs: torch.Tensor, translations: torch.Tensor) -> torch.Tensor:
    """Build ``[R(rotvec) | t]`` 4x4 transforms.

    Args:
        rotvecs: (..., 3) axis-angle vectors.
        translations: (..., 3) translations.

    Returns:
        (..., 4, 4) rigid transforms.
    """
    check_shape("rotvecs", rotvecs, (..., 3))
    check_shape("translations", translations, (..., 3))
    batch = rotvecs.shape[:-1]
    rot = batch_rodrigues(rotvecs.reshape(-1, 3)).reshape(*batch, 3, 3)
    out = torch.zeros(*batch, 4, 4, dtype=rotvecs.dtype, device=rotvecs.device)
    out[..., :3, :3] = rot
    out[..., :3, 3] = translations
    out[..., 3, 3] = 1.0
    return out


def world_from_joints(
    joint_rotvecs: torch.Tensor, rest_joints: torch.Tensor, world_from_smpl: torch.Tensor | None = None
) -> torch.Tensor:
    """Forward kinematics of the SMPL-24 tree.

    ``G_0 = [R(theta_0) | J_0]`` and ``G_j = G_par(j) [R(theta_j) | J_j - J_par(j)]``, then
    ``world_from_joint_j = world_from_smpl G_j``.

    Args:
        joint_rotvecs: (B, 24, 3) axis-angle per joint (SMPL ``poses`` reshaped; joint 0 is the global orient).
        rest_joints: (B, 24, 3) rest joint positions in the SMPL frame (``J_regressor @ v_shaped``).
        world_from_smpl: optional (B, 4, 4) global transform (ZJU ``[R(Rh) | Th]``).

    Returns:
        (B, 24, 4, 4) ``world_from_joint``: chained rotation, origin at the posed joint.
    """
    check_shape("joint_rotvecs", joint_rotvecs, (-1, N_JOINTS, 3))
    n_batch = joint_rotvecs.shape[0]
    rot_mats = batch_rodrigues(joint_rotvecs.reshape(-1, 3)).reshape(n_batch, N_JOINTS, 3, 3)
    return world_from_joint_rotations(rot_mats, rest_joints, world_from_smpl)


def world_from_joint_rotations(
    rot_mats: torch.Tensor, rest_joints: torch.Tensor, world_from_smpl: torch.Tensor | None = None
) -> torch.Tensor:
    """:func:`world_from_joints` with the local rotations given as matrices R(theta_j) (B, 24, 3, 3).

    Returns:
        (B, 24, 4, 4) ``world_from_joint``.
    """
    check_shape("rot_mats", rot_mats, (-1, N_JOINTS, 3, 3))
    check_shape("rest_joints", rest_joints, (rot_mats.shape[0], N_JOINTS, 3))
    n_batch = rot_mats.shape[0]
    parents = torch.tensor(SMPL_PARENTS, dtype=torch.long, device=rest_joints.device)
    posed_joints, skinning = batch_rigid_transform(rot_mats, rest_joints, parents, dtype=rest_joints.dtype)
    smpl_from_joint = skinning.clone()
    smpl_from_joint[..., :3, 3] = posed_joints
    if world_from_smpl is None:
        return smpl_from_joint
    check_shape("world_from_smpl", world_from_smpl, (n_batch, 4, 4))
    return world_from_smpl[:, None] @ smpl_from_joint


def parts_from_joints(world_from_joint: torch.Tensor) -> torch.Tensor:
    """Select the 19 NARF parts: (..., 24, 4, 4) -> (..., 19, 4, 4) ``world_from_part``."""
    check_shape("world_from_joint", world_from_joint, (..., N_JOINTS, 4, 4))
    return world_from_joint[..., list(PART_JOINTS), :, :]


def rest_offsets_from_world(world_from_joint: torch.Tensor) -> torch.Tensor:
    """Rest joints relative to the pelvis, recovered from posed joint frames (inverse of ``world_from_joints``).

    ``G_j = G_par(j) [R(theta_j) | J_j - J_par(j)]`` gives ``J_j - J_par(j) = R_par(j)^T (t_j - t_par(j))`` with R the
    chained rotation and t the posed joint, exactly, for any global transform (scale applies to t only).

    Args:
        world_from_joint: (..., 24, 4, 4) posed joint frames.

    Returns:
        (..., 24, 3) rest joints J_j - J_0 in the units of the translations.
    """
    check_shape("world_from_joint", world_from_joint, (..., N_JOINTS, 4, 4))
    rotation, position = world_from_joint[..., :3, :3], world_from_joint[..., :3, 3]
    offsets = [torch.zeros_like(position[..., 0, :])]
    for j in range(1, N_JOINTS):
        parent = SMPL_PARENTS[j]
        local = (
            rotation[..., parent, :, :].transpose(-1, -2) @ (position[..., j, :] - position[..., parent, :])[..., None]
        )
        offsets.append(offsets[parent] + local[..., 0])
    return torch.stack(offsets, dim=-2)


def retarget(world_from_joint: torch.Tensor, rest_offsets: torch.Tensor) -> torch.Tensor:
    """Joint frames with the rotations of ``world_from_joint`` on another skeleton: forward kinematics of the local
    rotations R_par(j)^T R_j over the rest offsets J_j - J_par(j) of ``rest_offsets``, from the same root frame.

    Args:
        world_from_joint: (B, 24, 4, 4) the motion's joint frames.
        rest_offsets: (B, 24, 3) the skeleton's rest joints relative to its pelvis (``rest_offsets_from_world``).

    Returns:
        (B, 24, 4, 4) joint frames of the skeleton in the motion's pose.
    """
    check_shape("world_from_joint", world_from_joint, (-1, N_JOINTS, 4, 4))
    check_shape("rest_offsets", rest_offsets, (world_from_joint.shape[0], N_JOINTS, 3))
    frames = [world_from_joint[:, 0]]
    for j in range(1, N_JOINTS):
        parent = SMPL_PARENTS[j]
        out = world_from_joint[:, j].clone()
        bone = (rest_offsets[:, j] - rest_offsets[:, parent])[..., None]
        out[:, :3, 3] = frames[parent][:, :3, 3] + (frames[parent][:, :3, :3] @ bone)[..., 0]
        frames.append(out)
    return torch.stack(frames, dim=1)


def bone_lengths(joint_positions: torch.Tensor) -> torch.Tensor:
    """Bone lengths zeta: ``zeta_c = |t_c - t_par(c)|`` for the 19 bones of ``BONE_CHILDREN``.

    Args:
        joint_positions: (..., 24, 3) joint positions (posed or rest; the result does not depend on pose).

    Returns:
        (..., 19) bone lengths in the units of the input.
    """
    check_shape("joint_positions", joint_positions, (..., N_JOINTS, 3))
    children = list(BONE_CHILDREN)
    parents = [SMPL_PARENTS[c] for c in children]
    return (joint_positions[..., children, :] - joint_positions[..., parents, :]).norm(dim=-1)


def kinematic_reach(joint_positions: torch.Tensor) -> torch.Tensor:
    """Kinematic reach s: the maximum over joints of the summed bone lengths along the chain from the pelvis.

    Args:
        joint_positions: (..., 24, 3) joint positions.

    Returns:
        (...,) reach, pose-invariant (about 1.1 m for an adult).
    """
    check_shape("joint_positions", joint_positions, (..., N_JOINTS, 3))
    lengths = [torch.zeros_like(joint_positions[..., 0, 0])]
    for j in range(1, N_JOINTS):
        parent = SMPL_PARENTS[j]
        bone = (joint_positions[..., j, :] - joint_positions[..., parent, :]).norm(dim=-1)
        lengths.append(lengths[parent] + bone)
    return torch.stack(lengths, dim=-1).amax(dim=-1)


def part_pose_features(world_from_part: torch.Tensor, reach: torch.Tensor) -> torch.Tensor:
    """Per-part pose features xi_i = log([R_i | (t_i - b) / s]) in the body frame (docs/model.md §1, decision d).

    The body frame has its origin at the posed pelvis ``b = t_0`` and world axes; the global translation is
    removed, the global orientation kept.

    Args:
        world_from_part: (B, 19, 4, 4) part transforms; part 0 is the pelvis.
        reach: (B,) kinematic reach s.

    Returns:
        (B, 19, 6) se(3) vectors ``[omega; u]``; divide by pi before encoding.
    """
    check_shape("world_from_part", world_from_part, (-1, N_PARTS, 4, 4))
    check_shape("reach", reach, (world_from_part.shape[0],))
    normalised = world_from_part.clone()
    pelvis = world_from_part[:, :1, :3, 3]
    normalised[..., :3, 3] = (world_from_part[..., :3, 3] - pelvis) / reach[:, None, None]
    return se3_log(normalised)


def vertex_parts(skinning_weights: torch.Tensor) -> torch.Tensor:
    """Assign each vertex to the part of its largest skinning weight (leaves go to their parents).

    Args:
        skinning_weights: (V, 24) LBS weights.

    Returns:
        (V,) long part index in [0, 19).
    """
    check_shape("skinning_weights", skinning_weights, (-1, N_JOINTS))
    lookup = torch.tensor(JOINT_TO_PART, dtype=torch.long, device=skinning_weights.device)
    return lookup[skinning_weights.argmax(dim=-1)]


def fit_part_boxes(
    vertices_world: torch.Tensor,
    world_from_part: torch.Tensor,
    reach: torch.Tensor,
    parts_of_vertices: torch.Tensor,
    scale_pad: float = 1.1,
    abs_pad: float = 0.03,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Fit one box per part, axis-aligned in the part frame, in body units (docs/model.md §1, decision a).

    Each vertex is mapped into its part's frame, ``x_i = R_i^T (v - t_i) / s``; the box spans the min/max over
    all given frames, then half-extents are padded ``h <- scale_pad * h + abs_pad``.

    Args:
        vertices_world: (F, V, 3) vertices of F frames (the rest pose counts as a frame with identity rotations).
        world_from_part: (F, 19, 4, 4) part transforms of the same frames.
        reach: (F,) kinematic reach s per frame.
        parts_of_vertices: (V,) part index of each vertex (``vertex_parts``).
        scale_pad: multiplicative padding of the half-extents.
        abs_pad: additive padding of the half-extents, in body units.

    Returns:
        centres (19, 3) and half_extents (19, 3), in body units.
    """
    check_shape("vertices_world", vertices_world, (-1, -1, 3))
    n_frames, n_verts = vertices_world.shape[:2]
    check_shape("world_from_part", world_from_part, (n_frames, N_PARTS, 4, 4))
    check_shape("reach", reach, (n_frames,))
    check_shape("parts_of_vertices", parts_of_vertices, (n_verts,))
    own = world_from_part[:, parts_of_vertices]  # (F, V, 4, 4)
    local = (own[..., :3, :3].transpose(-1, -2) @ (vertices_world - own[..., :3, 3])[..., None])[..., 0]
    local = local / reach[:, None, None]
    lows, highs = [], []
    for part in range(N_PARTS):
        points = local[:, parts_of_vertices == part].reshape(-1, 3)
        if points.shape[0] == 0:
            raise ValueError(f"part {part} ({JOINT_NAMES[PART_JOINTS[part]]}) owns no vertex; check the weights")
        lows.append(points.amin(dim=0))
        highs.append(points.amax(dim=0))
    low, high = torch.stack(lows), torch.stack(highs)
    return (low + high) / 2, scale_pad * (high - low) / 2 + abs_pad
