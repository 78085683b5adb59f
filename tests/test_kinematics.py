import math

import numpy as np
import torch

from narf.geometry import se3_exp
from narf.kinematics import (
    BONE_CHILDREN,
    JOINT_TO_PART,
    PART_JOINTS,
    PART_PARENTS,
    SMPL_PARENTS,
    bone_lengths,
    fit_part_boxes,
    kinematic_reach,
    part_pose_features,
)
from pipelines.body.model import smplx_params_from_zju


def _random_zju(n, seed, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    poses = 0.4 * torch.randn(n, 72, generator=gen, dtype=dtype)
    poses[:, :3] = 0
    rh = torch.randn(n, 3, generator=gen, dtype=dtype)
    th = torch.randn(n, 3, generator=gen, dtype=dtype)
    shapes = torch.randn(n, 10, generator=gen, dtype=dtype)
    return poses, rh, th, shapes


def test_part_tables_match_model_md():
    assert PART_PARENTS == tuple(-1 if SMPL_PARENTS[j] < 0 else PART_JOINTS.index(SMPL_PARENTS[j]) for j in PART_JOINTS)
    assert [JOINT_TO_PART[j] for j in (10, 11, 15, 22, 23)] == [7, 8, 10, 17, 18]
    assert len(BONE_CHILDREN) == 19 and not {2, 3, 13, 14} & set(BONE_CHILDREN)


def test_transforms_agree_with_smplx_under_rh_th(body_model64):
    poses, rh, th, shapes = _random_zju(6, 1)
    poses[:3, :3] = 0.3  # a non-zero root pose too
    body = body_model64.pose_zju(poses, rh, th, shapes)
    ref = body_model64.smpl(**smplx_params_from_zju(body_model64, poses, rh, th, shapes))
    # float64 on both sides; the smplx path adds transl = Th + R(Rh) J0 - J0 (docs/formats.md §1.6) while ours
    # rotates about the SMPL origin: equal in exact arithmetic. 1e-5 m (10 um) is the scale of the float32 vertex
    # files this conversion must reproduce; a convention error (rotation about the pelvis) is ~0.1 m
    assert (ref.vertices - body.vertices).abs().max() < 1e-5
    assert (ref.joints[:, :24] - body.world_from_joint[..., :3, 3]).abs().max() < 1e-5
    # Rotations: a rest-frame vertex offset mapped by world_from_joint equals smplx's skinning of that offset.
    from smplx.lbs import batch_rigid_transform, batch_rodrigues

    rot_mats = batch_rodrigues(poses.reshape(-1, 3)).reshape(6, 24, 3, 3)
    _, skinning = batch_rigid_transform(rot_mats, body.rest_joints, body_model64.smpl.parents, dtype=torch.float64)
    from kornia.geometry.conversions import axis_angle_to_rotation_matrix

    rot_rh = axis_angle_to_rotation_matrix(rh)
    # float64 products of up to 8 chained rotations: ~8 * 3 eps64 per entry ~ 5e-15
    assert torch.allclose(body.world_from_joint[..., :3, :3], rot_rh[:, None] @ skinning[..., :3, :3], atol=1e-10)


def test_fk_against_slow_loop(body_model64):
    poses, rh, th, shapes = _random_zju(2, 2)
    body = body_model64.pose_zju(poses, rh, th, shapes)
    from kornia.geometry.conversions import axis_angle_to_rotation_matrix

    rots = axis_angle_to_rotation_matrix(poses.reshape(-1, 3)).reshape(2, 24, 3, 3)
    for b in range(2):
        world = [None] * 24
        rest = body.rest_joints[b]
        root = torch.eye(4, dtype=torch.float64)
        root[:3, :3] = axis_angle_to_rotation_matrix(rh[b : b + 1])[0]
        root[:3, 3] = th[b]
        for j in range(24):
            local = torch.eye(4, dtype=torch.float64)
            local[:3, :3] = rots[b, j]
            parent = SMPL_PARENTS[j]
            local[:3, 3] = rest[j] - (rest[parent] if parent >= 0 else 0)
            world[j] = (root if parent < 0 else world[parent]) @ local
        # float64, the same chain of <= 8 products in the same order: rounding ~1e-15 on values ~1
        assert torch.allclose(torch.stack(world), body.world_from_joint[b], atol=1e-10)


def test_bone_lengths_pose_invariant_and_hand_computed(body_model64):
    poses, rh, th, shapes = _random_zju(3, 3)
    body = body_model64.pose_zju(poses, rh, th, shapes[:1].expand(3, 10))
    # float64 norms of differences of posed joints ~1 m apart: pose changes them only by rounding (~1e-15)
    assert torch.allclose(body.bone_lengths, body.bone_lengths[:1].expand(3, 19), atol=1e-10)
    joints = body.world_from_joint[0, :, :3, 3]
    assert math.isclose(body.bone_lengths[0, 1].item(), (joints[4] - joints[1]).norm().item(), rel_tol=1e-12)
    assert torch.allclose(body.reach, body.reach[:1].expand(3), atol=1e-10)
    # Reach of a straight chain: hand-computed.
    positions = torch.zeros(24, 3, dtype=torch.float64)
    for j in range(1, 24):
        positions[j] = positions[SMPL_PARENTS[j]] + torch.tensor([0.0, 0.1, 0.0], dtype=torch.float64)
    # pelvis..hand: 8 bones; a float64 sum of 8 values of 0.1 (each inexact in binary): ~8 eps64 relative
    assert math.isclose(kinematic_reach(positions).item(), 0.1 * 8, rel_tol=1e-12)
    assert torch.allclose(bone_lengths(positions), torch.full((19,), 0.1, dtype=torch.float64))


def test_pose_features_are_bounded_and_invariant_to_translation(body_model64):
    poses, rh, th, shapes = _random_zju(4, 4)
    body = body_model64.pose_zju(poses, rh, th, shapes)
    moved = body_model64.pose_zju(poses, rh, th + 5.0, shapes)
    # float64: moving by 5 m changes t_i - b by rounding of 5 (~1e-15), divided by s ~ 1; the log's conditioning
    # is ~1 away from theta = pi
    assert torch.allclose(body.pose_features, moved.pose_features, atol=1e-9)
    assert (body.pose_features / math.pi).abs().max() <= 1.0
    recon = se3_exp(body.pose_features)
    assert torch.allclose(recon[..., :3, :3], body.world_from_part[..., :3, :3], atol=1e-8)  # as above, exp(log R)


def test_part_boxes_contain_their_vertices(body_model):
    rest = body_model.rest_body(torch.zeros(1, 10))
    poses, rh, th, shapes = _random_zju(3, 5, torch.float32)
    posed = body_model.pose_zju(poses, rh, th, torch.zeros(3, 10))
    centres, half = body_model.part_boxes([rest, posed], scale_pad=1.0, abs_pad=0.0)
    parts = body_model.parts_of_vertices
    for body in (rest, posed):
        own = body.world_from_part[:, parts]
        local = (own[..., :3, :3].transpose(-1, -2) @ (body.vertices - own[..., :3, 3])[..., None])[..., 0]
        u = (local / body.reach[:, None, None] - centres[parts]) / half[parts]
        assert u.abs().max() <= 1 + 1e-5
    centres2, half2 = fit_part_boxes(rest.vertices, rest.world_from_part, rest.reach, parts)
    assert (half2 > half.min()).all() and np.isfinite(centres2.numpy()).all()


def test_part_pose_features_shape_error():
    import pytest

    with pytest.raises(ValueError, match="world_from_part"):
        part_pose_features(torch.zeros(2, 24, 4, 4), torch.ones(2))
