"""The colour's left-right symmetry (docs/model.md §6, *Left-right symmetry*): SMPL's mirror-image pose against
the reflected body, the reflected rays and the symmetry error by hand, and the term in a fit."""

import pytest
import torch

from fitting.config import load_config
from fitting.run_folder import prepare_run_dir
from fitting.unseen import mirror_colour_loss, mirror_rays, symmetry_error
from narf.fields import PoseBatch
from narf.geometry import se3_exp
from pipelines.body.mirror import SMPL_MIRROR, mirror_smpl_poses
from pipelines.body.model import pose_batch, posed_from_rest_joints
from pipelines.runs.fit import start_run


def test_the_mirror_pose_by_hand():
    """The left elbow's rotation (0.1, 0.2, 0.3) becomes the right elbow's (0.1, -0.2, -0.3) and the left elbow takes
    the right one's (0 here); the root stays; mirroring twice gives the pose back exactly (swaps and sign flips)."""
    poses = torch.zeros(72, dtype=torch.float64)
    poses[:3] = torch.tensor([0.5, -0.4, 0.3], dtype=torch.float64)
    poses[18 * 3 : 19 * 3] = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    mirrored = torch.as_tensor(mirror_smpl_poses(poses.numpy()))
    assert mirrored[19 * 3 : 20 * 3].tolist() == [0.1, -0.2, -0.3] and mirrored[18 * 3 : 19 * 3].tolist() == [0, 0, 0]
    assert mirrored[:3].tolist() == [0.5, -0.4, 0.3]
    batch = torch.randn(4, 72).numpy()
    assert (mirror_smpl_poses(mirror_smpl_poses(batch)) == batch).all()
    assert sorted(SMPL_MIRROR) == list(range(24)) and all(SMPL_MIRROR[SMPL_MIRROR[j]] == j for j in range(24))


def test_the_mirror_pose_is_the_reflected_body(body_model64):
    """On a skeleton made left-right symmetric, the body posed in the mirror-image pose has each joint where the
    reflection of the original body (about the plane through its pelvis normal to the root's x axis, mirror_rays)
    puts its mirror joint, in random poses and world placements. float64, about ten chained 4x4 products on
    coordinates of a metre or two: 1e-12; a wrong sign or swap moves joints by centimetres."""
    gen = torch.Generator().manual_seed(4)
    rest = body_model64.rest_joints(torch.zeros(1, 10, dtype=torch.float64))[0]
    reflected_rest = rest[list(SMPL_MIRROR)] * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    symmetric = ((rest + reflected_rest) / 2).expand(3, 24, 3)
    poses = 0.6 * torch.randn(3, 72, generator=gen, dtype=torch.float64)
    world_from_smpl = se3_exp(torch.randn(3, 6, generator=gen, dtype=torch.float64))
    body = posed_from_rest_joints(poses, world_from_smpl, symmetric)
    mirror = posed_from_rest_joints(torch.as_tensor(mirror_smpl_poses(poses.numpy())), world_from_smpl, symmetric)
    joints = body.world_from_joint[..., :3, 3]
    frames = torch.arange(3).repeat_interleave(24)
    reflected, _ = mirror_rays(joints.reshape(-1, 3), joints.reshape(-1, 3), frames, pose_batch(body))
    expected = reflected.reshape(3, 24, 3)[:, list(SMPL_MIRROR)]
    assert torch.allclose(mirror.world_from_joint[..., :3, 3], expected, atol=1e-12)
    assert (joints[:, 18] - expected[:, 18]).norm(dim=-1).min() > 0.01  # the elbows do move: the test can fail


def test_mirror_rays_by_hand():
    """A pelvis at (1, 2, 3) turned 90 degrees about z (its x axis along world y): the plane is y = 2, so (4, 5, 6)
    -> (4, -1, 6) and the direction (0, 1, 0) -> (0, -1, 0); a point on the plane stays."""
    world_from_part = torch.eye(4, dtype=torch.float64).repeat(1, 19, 1, 1)
    world_from_part[0, 0, :3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    world_from_part[0, 0, :3, 3] = torch.tensor([1.0, 2.0, 3.0])
    zeros = (torch.zeros(1, 19), torch.zeros(1, 19, 6), torch.zeros(1, 19, 3))
    poses = PoseBatch(world_from_part, torch.ones(1), *zeros)
    origins = torch.tensor([[4.0, 5.0, 6.0], [7.0, 2.0, -1.0]], dtype=torch.float64)
    dirs = torch.tensor([[0.0, 1.0, 0.0], [0.6, 0.0, 0.8]], dtype=torch.float64)
    reflected, reflected_dirs = mirror_rays(origins, dirs, torch.zeros(2, dtype=torch.long), poses)
    assert reflected.tolist() == [[4.0, -1.0, 6.0], [7.0, 2.0, -1.0]]
    assert reflected_dirs.tolist() == [[0.0, -1.0, 0.0], [0.6, 0.0, 0.8]]


def test_the_symmetry_error_by_hand():
    """Three pairs: opaque both (M = 1, 0.8), one ray at 0.3 (left out), opaque but the same colour. Colours C / M:
    (0.5, 0.5, 0.5) against (0.25, 0.5, 0.75) weigh 0.8 with |d|^2 = 0.125; the third weighs 0.9 with 0. The error
    is 0.8 * 0.125 / (3 * 1.7); with no opaque pair, 0."""
    rgb = torch.tensor([[0.5, 0.5, 0.5], [0.1, 0.1, 0.1], [0.9, 0.0, 0.45]])
    mask = torch.tensor([1.0, 0.3, 1.0])
    rgb_mirror = torch.tensor([[0.2, 0.4, 0.6], [0.2, 0.2, 0.2], [0.81, 0.0, 0.405]])
    mask_mirror = torch.tensor([0.8, 1.0, 0.9])
    expected = 0.8 * 0.125 / (3 * 1.7)
    # float32 of values <= 1 through a few operations: 1e-6
    assert symmetry_error(rgb, mask, rgb_mirror, mask_mirror).item() == pytest.approx(expected, abs=1e-6)
    assert symmetry_error(rgb[1:2], mask[1:2], rgb_mirror[1:2], mask_mirror[1:2]).item() == 0


def test_the_symmetry_term_reaches_the_field(data_root_64, tmp_path):
    """In a fit with train.mirror_weight the data holds the mirror-image poses, the term gives the field's weights a
    gradient, and with the weight at 0 it draws and renders nothing (the fit's generator does not move)."""
    sets = [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=3", "train.mirror_weight=1.0"]
    sets += ["train.mirror_rays=64"]
    trainer = start_run(
        prepare_run_dir(tmp_path / "run", False), torch.device("cpu"), load_config("tiny", sets), progress=False
    )
    trainer.fit()  # the term inside a step, end to end
    mirrored = trainer.fit_data.mirrored_poses
    assert mirrored.world_from_part.shape == trainer.views.poses.world_from_part.shape
    assert not torch.allclose(mirrored.pose_features, trainer.views.poses.pose_features)
    trainer.field.zero_grad()
    frames = torch.arange(2)
    term = mirror_colour_loss(trainer.config, trainer.field, trainer.views.poses, mirrored, frames, trainer.generator)
    term.backward()
    grads = [p.grad.abs().sum().item() for p in trainer.field.parameters() if p.grad is not None]
    assert grads and max(grads) > 0
    state = trainer.generator.get_state()
    off = load_config("tiny", [*sets, "train.mirror_weight=0"])
    assert mirror_colour_loss(off, trainer.field, trainer.views.poses, mirrored, frames, trainer.generator) == 0.0
    assert torch.equal(trainer.generator.get_state(), state)
