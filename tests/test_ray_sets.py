"""A training step's ray sets in one render (fitting.training_rays.render_ray_sets): the step's loss and every
gradient against each set rendered by a call of its own, the outputs split back per set, and the poses of several
batches concatenated."""

from contextlib import ExitStack
from dataclasses import replace
from unittest import mock

import pytest
import torch

from fitting.config import load_config
from fitting.losses import ray_loss
from fitting.run_folder import prepare_run_dir
from fitting.training_rays import RaySet, render_each_set, render_ray_sets, render_training_rays
from narf.fields import PoseBatch
from narf.fields.common import cat_poses
from pipelines.runs.fit import start_run

#: the unseen views' terms and the symmetry on, few virtual rays: every kind of set a step renders
TERMS = ["train.mirror_weight=1.0", "train.mirror_rays=48", "train.entropy_weight=0.05", "train.virtual_rays=40"]
TERMS += ["train.smoothness_weight=0.5", "train.virtual_patches=1"]
#: gamma_10 with 2^0 and 2^1 open alone (docs/model.md §2's window held at its start): a sample's depth enters the
#: first layers through sin(2^k pi u), whose top frequency turns a float32 ulp of depth into 10^4 times as much feature;
#: see test_one_render_of_every_set_equals_each_set_alone
TERMS += ["train.window_steps=1000000", "train.window_start=2"]


def _trainer(data_root, folder, extra=()):
    sets = [f"data.data_root={data_root}", "data.ratio=1.0", "train.steps=2", *TERMS, *extra]
    trainer = start_run(prepare_run_dir(folder, False), torch.device("cpu"), load_config("tiny", sets), progress=False)
    trainer.fit()  # a trained field and a refreshed occupancy grid
    return trainer


def _step(trainer, alone: bool):
    """One training step's loss and the field's gradients, the optimiser not stepped; ``alone``: every set rendered by
    a call of its own (the reference), counting the renders."""
    calls = []

    def count(*args, **kwargs):
        calls.append(len(args[2]))
        return render_training_rays(*args, **kwargs)

    state, seen = trainer.generator.get_state(), {}
    trainer.field.zero_grad()

    def keep(loss, colour):
        loss.backward()
        seen["loss"], seen["colour"] = loss.detach(), colour.detach()
        return 0.0, 0.0

    with ExitStack() as patches:
        patches.enter_context(mock.patch.object(trainer, "optimise", keep))
        patches.enter_context(mock.patch("fitting.training_rays.render_training_rays", side_effect=count))
        if alone:
            patches.enter_context(mock.patch("fitting.trainer.render_ray_sets", render_each_set))
        trainer.train_step()
    trainer.generator.set_state(state)
    grads = {k: p.grad.clone() for k, p in trainer.field.named_parameters() if p.grad is not None}
    return seen, grads, calls


@pytest.fixture(scope="module")
def trainer(data_root_64, tmp_path_factory):
    """A tiny fit with every kind of set on, 2 steps trained (the tests below leave its weights and generator as
    they found them)."""
    return _trainer(data_root_64, tmp_path_factory.mktemp("ray_sets") / "run")


def test_one_render_of_every_set_equals_each_set_alone(trainer):
    """The step renders the training rays, the entropy's and the smoothness's virtual rays and the symmetry's rays
    and their mirror images (5 sets) in one call, with the loss and every gradient of 5 calls.

    Tolerances: float32 sums over a few thousand samples whose matrix products are blocked differently in one batch
    than in five (relative rounding about sqrt(n) eps, n ~ 10^4: 1e-5), so 1e-4 for the loss and the colours. A
    coarse density one ulp apart (the blocking) moves a fine sample's inverse-CDF depth by ~1e-7, which sin(2^9 pi u
    / h) multiplies by ~10^4 in the features that the density's first block and the selector take as they are: with
    every frequency open their gradients lie up to 1.5 % apart on one thread (measured). With 2^1 the top frequency open
    (TERMS) that is 256 times less, about 6e-5, so each gradient's difference is held within 1e-3 of its norm; a set
    left out of the one render, or its gradient cut, moves a gradient by its whole share."""
    together, grads, calls = _step(trainer, alone=False)
    reference, grads_alone, calls_alone = _step(trainer, alone=True)
    assert len(calls) == 1 and len(calls_alone) == 5
    assert calls[0] == sum(calls_alone)  # the same rays
    torch.testing.assert_close(together["loss"], reference["loss"], rtol=1e-4, atol=0)
    torch.testing.assert_close(together["colour"], reference["colour"], rtol=1e-4, atol=0)
    assert grads.keys() == grads_alone.keys() and grads
    for key, grad in grads.items():
        assert (grad - grads_alone[key]).norm() <= 1e-3 * grads_alone[key].norm(), key


def test_each_set_gets_its_own_rays_hits_and_frames(trainer):
    """Split back per set: a set whose rays all miss the body has no hits (C = 0, M = 0, no sample weights), the others'
    hit indices count from their own first ray, and a set of other poses is rendered in its own frames (the same rays
    in a pose moved 10 reaches away miss)."""
    poses, config = trainer.views.poses, trainer.config
    pelvis = poses.world_from_part[0, 0, :3, 3]
    n, generator = 16, torch.Generator().manual_seed(0)
    origins = (pelvis + torch.tensor([0.0, -3.0, 0.0]) * poses.reach[0]).expand(n, 3)
    dirs = torch.nn.functional.normalize(pelvis - origins + 0.05 * torch.randn(n, 3, generator=generator), dim=-1)
    frames = torch.zeros(n, dtype=torch.long)
    uniforms = [torch.rand(n, 8, generator=generator) for _ in range(2)]
    moved = replace(poses, world_from_part=poses.world_from_part.clone())
    moved.world_from_part[:, :, :3, 3] += 10 * poses.reach[:, None, None]
    hits = RaySet(origins, dirs, frames, poses, uniforms)
    misses = RaySet(origins, dirs, frames, moved, uniforms)
    with torch.no_grad():
        a, b, c = render_ray_sets(config, trainer.field, [hits, misses, hits], 8, 8)
        (alone,) = render_ray_sets(config, trainer.field, [hits], 8, 8)
    assert b.sample_weights is None and b.hit_ids is None
    assert torch.equal(b.rgb, torch.zeros(n, 3)) and torch.equal(b.mask, torch.zeros(n))
    assert alone.hit_ids.numel() == n and alone.mask.min() > 0  # every ray meets the body's boxes
    for out in (a, c):
        assert torch.equal(out.hit_ids, alone.hit_ids)
        torch.testing.assert_close(out.rgb, alone.rgb, rtol=1e-5, atol=1e-6)  # float32, blocked differently
        torch.testing.assert_close(out.sample_weights, alone.sample_weights, rtol=1e-5, atol=1e-6)


def test_cat_poses_by_hand():
    """Frames one after another; an appearance code missing from a batch is zeros there; world_from_joint only when
    every batch has it."""

    def batch(frames, value, appearance=None, joints=False):
        eye = torch.eye(4).repeat(frames, 19, 1, 1)
        eye[:, :, 0, 3] = value
        wfj = torch.eye(4).repeat(frames, 24, 1, 1) if joints else None
        zeros = (torch.zeros(frames, 19), torch.zeros(frames, 19, 6), torch.zeros(frames, 19, 3))
        return PoseBatch(eye, torch.full((frames,), value), *zeros, wfj, appearance)

    a, b = batch(2, 1.0, torch.ones(2, 3), joints=True), batch(1, 2.0)
    both = cat_poses([a, b])
    assert both.reach.tolist() == [1.0, 1.0, 2.0]
    assert both.world_from_part[:, 0, 0, 3].tolist() == [1.0, 1.0, 2.0]
    assert torch.equal(both.appearance, torch.tensor([[1.0] * 3, [1.0] * 3, [0.0] * 3]))
    assert both.world_from_joint is None
    assert cat_poses([a, a]).world_from_joint.shape == (4, 24, 4, 4)
    assert cat_poses([b, b]).appearance is None


def test_the_loss_composites_a_white_background_as_the_renderer_does(data_root_64, tmp_path):
    """Sets are rendered on black, and the loss composites the data's white background, C + (1 - M) bg: the loss and
    colour MSE of rays rendered by the renderer's own compositing onto white (render_rays' background=1), by hand.
    Tolerance: float32, the same sums in another order (one addition of (1 - M) per channel)."""
    trainer = _trainer(data_root_64, tmp_path / "run", ["train.mirror_weight=0", "data.white_background=true"])
    config, t, generator = trainer.config, trainer.config.train, torch.Generator().manual_seed(1)
    batch = trainer.views.sample(4, 32, t.body_fraction, t.border_fraction, generator)
    uniforms = [torch.rand(len(batch.frames), 8, generator=generator) for _ in range(2)]
    poses = trainer.views.poses
    with torch.no_grad():
        loss, colour = ray_loss(config, trainer.field, batch, poses, None, 8, 8, uniforms=uniforms)
        white = render_training_rays(
            config,
            trainer.field,
            batch.origins,
            batch.dirs,
            batch.frames,
            poses,
            8,
            8,
            background=1.0,
            uniforms=uniforms,
        )
    assert (white.mask < 0.99).any()  # the background shows
    by_hand = (white.rgb - batch.rgb).square().sum() / white.rgb.numel()
    mask_term = (batch.mask_weight * (white.mask - batch.mask).square()).sum() / batch.mask_weight.sum()
    torch.testing.assert_close(colour, by_hand, rtol=1e-5, atol=0)
    torch.testing.assert_close(loss, by_hand + t.mask_weight * mask_term, rtol=1e-5, atol=0)
