"""Views nobody trained on (fitting.unseen): virtual cameras around the body and InfoNeRF's ray entropy, against
hand values; the term reaches the field in a fit."""

import math

import pytest
import torch

from fitting.config import load_config
from fitting.run_folder import prepare_run_dir
from fitting.unseen import VIRTUAL_DISTANCE, VIRTUAL_SPREAD, ray_entropy, virtual_rays
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
    entropy = trainer.unseen_entropy(trainer.views.poses, trainer.views.frame_of_image)
    assert entropy.item() > 0
    entropy.backward()
    grads = [p.grad.abs().sum().item() for p in trainer.field.parameters() if p.grad is not None]
    assert grads and max(grads) > 0
