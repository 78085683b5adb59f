"""Views nobody trained on (fitting.unseen): virtual cameras around the body and InfoNeRF's ray entropy, against
hand values; the term reaches the field in a fit."""

import math

import pytest
import torch

from fitting.config import load_config
from fitting.run_folder import prepare_run_dir
from fitting.unseen import (
    PATCH_PITCH,
    PATCH_SIDE,
    VIRTUAL_DISTANCE,
    VIRTUAL_SPREAD,
    depth_smoothness,
    ray_entropy,
    unseen_views_loss,
    virtual_patches,
    virtual_rays,
)
from narf.fields import PoseBatch
from pipelines.runs.fit import start_run


def test_ray_entropy_hand_values():
    """Two equal weights: log 2; one weight: 0; four equal: log 4; a ray of opacity 0.05 is left out of the mean."""
    weights = torch.tensor([[0.4, 0.4, 0.0, 0.0], [0.0, 0.9, 0.0, 0.0], [0.2, 0.2, 0.2, 0.2], [0.05, 0.0, 0.0, 0.0]])
    expected = (math.log(2) + 0 + math.log(4)) / 3
    assert ray_entropy(weights).item() == pytest.approx(expected, abs=1e-6)  # float32 logs of exact fractions
    assert ray_entropy(weights[3:]).item() == 0 and ray_entropy(None).item() == 0


def test_virtual_rays_start_around_the_body_and_aim_at_it():
    """Each ray starts VIRTUAL_DISTANCE reaches from its frame's pelvis and passes within the aim cube's half
    diagonal (sqrt(3) VIRTUAL_SPREAD reaches) of it; only the frames given are drawn."""
    n_frames = 3
    world_from_part = torch.eye(4).repeat(n_frames, 19, 1, 1)
    world_from_part[:, 0, :3, 3] = torch.tensor([[0.0, 0.0, 1.0], [2.0, 1.0, 0.9], [-1.0, 3.0, 1.1]])
    reach = torch.tensor([1.0, 1.2, 0.9])
    poses = PoseBatch(
        world_from_part, reach, torch.zeros(n_frames, 19), torch.zeros(n_frames, 19, 6), torch.zeros(n_frames, 19, 3)
    )
    origins, dirs, frame = virtual_rays(poses, torch.tensor([0, 2]), 500, torch.Generator().manual_seed(0))
    assert set(frame.tolist()) == {0, 2}
    pelvis, s = world_from_part[frame, 0, :3, 3], reach[frame]
    # float32 at metre scale: 1e-5
    assert torch.allclose((origins - pelvis).norm(dim=-1), VIRTUAL_DISTANCE * s, atol=1e-5)
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(500), atol=1e-6)
    to_pelvis = pelvis - origins
    nearest = (to_pelvis - (to_pelvis * dirs).sum(-1, keepdim=True) * dirs).norm(dim=-1)
    assert (nearest <= math.sqrt(3) * VIRTUAL_SPREAD * s + 1e-5).all()


def test_the_entropy_term_reaches_the_field(data_root_64, tmp_path):
    """In a fit with train.entropy_weight, the virtual rays' entropy alone gives the field's weights a gradient."""
    sets = [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=3", "train.entropy_weight=0.01"]
    trainer = start_run(
        prepare_run_dir(tmp_path / "run", False), torch.device("cpu"), load_config("tiny", sets), progress=False
    )
    trainer.fit()  # the term inside a step, end to end
    trainer.field.zero_grad()
    entropy = unseen_views_loss(trainer.config, trainer.field, trainer.views.poses, torch.arange(2), trainer.generator)
    assert entropy.item() > 0
    entropy.backward()
    grads = [p.grad.abs().sum().item() for p in trainer.field.parameters() if p.grad is not None]
    assert grads and max(grads) > 0


def _standing_poses(n_frames=3):
    world_from_part = torch.eye(4).repeat(n_frames, 19, 1, 1)
    world_from_part[:, 0, :3, 3] = torch.tensor([[0.0, 0.0, 1.0], [2.0, 1.0, 0.9], [-1.0, 3.0, 1.1]])[:n_frames]
    reach = torch.tensor([1.0, 1.2, 0.9])[:n_frames]
    zeros = (torch.zeros(n_frames, 19), torch.zeros(n_frames, 19, 6), torch.zeros(n_frames, 19, 3))
    return PoseBatch(world_from_part, reach, *zeros)


def test_virtual_patches_are_square_grids_of_rays_from_one_camera():
    """Every patch's S^2 rays leave one origin VIRTUAL_DISTANCE reaches from its pelvis; neighbouring rays are
    PATCH_PITCH reaches apart across the centre's plane (distance d, pitch p: the angle between two rays one pixel
    apart near the centre is about p / d), and each patch's rows and columns are square to each other."""
    poses = _standing_poses()
    origins, dirs, frame = virtual_patches(poses, torch.tensor([1, 2]), 5, torch.Generator().manual_seed(1))
    per = PATCH_SIDE * PATCH_SIDE
    assert origins.shape == (5 * per, 3) and set(frame.tolist()) <= {1, 2}
    origins, dirs, frame = origins.reshape(5, per, 3), dirs.reshape(5, PATCH_SIDE, PATCH_SIDE, 3), frame.reshape(5, per)
    assert (origins == origins[:, :1]).all() and (frame == frame[:, :1]).all()
    s = poses.reach[frame[:, 0]]
    pelvis = poses.world_from_part[frame[:, 0], 0, :3, 3]
    torch.testing.assert_close((origins[:, 0] - pelvis).norm(dim=-1), VIRTUAL_DISTANCE * s)
    c = PATCH_SIDE // 2
    across = torch.acos((dirs[:, c, c] * dirs[:, c, c - 1]).sum(-1).clamp(max=1))
    down = torch.acos((dirs[:, c, c] * dirs[:, c - 1, c]).sum(-1).clamp(max=1))
    # the aim point lies 1.4-2.6 reaches away (VIRTUAL_DISTANCE minus / plus the aim cube's half-diagonal)
    lo, hi = (
        PATCH_PITCH / (VIRTUAL_DISTANCE + 3**0.5 * VIRTUAL_SPREAD),
        PATCH_PITCH / (VIRTUAL_DISTANCE - 3**0.5 * VIRTUAL_SPREAD),
    )
    assert ((across > 0.95 * lo) & (across < 1.05 * hi)).all() and torch.allclose(across, down, rtol=0.02)
    row, col = dirs[:, c, c + 1] - dirs[:, c, c - 1], dirs[:, c + 1, c] - dirs[:, c - 1, c]
    assert (torch.nn.functional.cosine_similarity(row, col, dim=-1).abs() < 0.01).all()


def test_depth_smoothness_hand_values():
    """A flat patch costs 0; one pixel 0.2 reaches deeper than its 3x3 patch's others at full opacity costs
    (4 pairs x 0.04) / 12 pairs; the same pixel at zero opacity costs 0 (its pairs weigh nothing); the reach divides."""
    opacity = torch.ones(1, 3, 3)
    flat = torch.full((1, 3, 3), 2.0)
    assert depth_smoothness(flat, opacity, torch.ones(1)).item() == 0
    step = flat.clone()
    step[0, 1, 1] = 2.2
    assert depth_smoothness(step, opacity, torch.ones(1)).item() == pytest.approx(4 * 0.04 / 12, rel=1e-5)
    assert depth_smoothness(step * 2, opacity, torch.full((1,), 2.0)).item() == pytest.approx(4 * 0.04 / 12, rel=1e-5)
    hidden = opacity.clone()
    hidden[0, 1, 1] = 0
    assert depth_smoothness(step * hidden, hidden, torch.ones(1)).item() == 0


def test_the_smoothness_term_reaches_the_field(data_root_64, tmp_path):
    """In a fit with train.smoothness_weight, the virtual patches' smoothness alone gives the field's weights a
    gradient (through the depths of a field that is not yet flat)."""
    sets = [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=3", "train.smoothness_weight=1"]
    trainer = start_run(
        prepare_run_dir(tmp_path / "run", False), torch.device("cpu"), load_config("tiny", sets), progress=False
    )
    trainer.fit()
    trainer.field.zero_grad()
    smoothness = unseen_views_loss(
        trainer.config, trainer.field, trainer.views.poses, torch.arange(2), trainer.generator
    )
    assert smoothness.item() > 0
    smoothness.backward()
    grads = [p.grad.abs().sum().item() for p in trainer.field.parameters() if p.grad is not None]
    assert grads and max(grads) > 0
