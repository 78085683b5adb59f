"""S3IM, the structural similarity over random groups of the training rays (fitting/losses.py; docs/model.md §6)."""

from __future__ import annotations

import kornia
import pytest
import torch

from fitting.config import ConfigError, FitConfig, load_config
from fitting.data import RayBatch
from fitting.losses import SIDE, grouped_ssim, stochastic_ssim_loss, structure_term
from narf.renderer import RenderOutput


def _pair(groups: int, side: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    x = torch.rand(groups * side**2, 3, generator=generator, dtype=torch.float64)
    noise = 0.3 * torch.rand(x.shape, generator=generator, dtype=torch.float64)
    return x, (0.8 * x + noise).clamp(0, 1)


def test_grouped_ssim_is_kornias_ssim_of_each_patch():
    """Each group laid out as a 5 x 5 patch (kornia needs an odd window) is kornia's SSIM of that patch with a
    window of its size and no padding. float64: the two differ by kornia's 1e-12 guard in the denominator only."""
    x, y = _pair(4, 5)
    ours = grouped_ssim(x, y, side=5)
    for g in range(4):
        patch = [t[g * 25 : (g + 1) * 25].T.reshape(1, 3, 5, 5) for t in (x, y)]
        theirs = kornia.metrics.ssim(*patch, 5, padding="valid").reshape(3)
        torch.testing.assert_close(ours[g], theirs, rtol=0, atol=1e-9)


def test_grouped_ssim_by_hand_with_the_4x4_window():
    """The default group (4 x 4 under a Gaussian of sigma 1.5, S3IM's kernel) against the formula written out
    pixel by pixel; identical inputs give 1 exactly up to rounding (float64)."""
    x, y = _pair(3, SIDE, seed=1)
    g = torch.exp(-((torch.arange(4, dtype=torch.float64) - 1.5) ** 2) / (2 * 1.5**2))
    w = (g[:, None] * g[None, :]).flatten() / (g.sum() ** 2)
    expected = torch.empty(3, 3, dtype=torch.float64)
    for group in range(3):
        for c in range(3):
            a, b = x[group * 16 : (group + 1) * 16, c], y[group * 16 : (group + 1) * 16, c]
            ma, mb = (w * a).sum(), (w * b).sum()
            va, vb = (w * (a - ma) ** 2).sum(), (w * (b - mb) ** 2).sum()
            cov = (w * (a - ma) * (b - mb)).sum()
            c1, c2 = 0.01**2, 0.03**2
            expected[group, c] = (2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
    torch.testing.assert_close(grouped_ssim(x, y), expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(grouped_ssim(x, x), torch.ones(3, 3, dtype=torch.float64), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="whole groups"):
        grouped_ssim(x[:-1], y[:-1])


def test_the_stochastic_loss_groups_rays_at_random():
    """0 for a perfect render; one ordering's loss is 1 - the mean SSIM of its groups; rays past the last whole
    group are left out of an ordering, and a batch smaller than a group gives 0 with a gradient path."""
    x, y = _pair(8, SIDE, seed=2)
    generator = torch.Generator().manual_seed(5)
    assert float(stochastic_ssim_loss(x, x, 10, generator)) == pytest.approx(0.0, abs=1e-12)
    order = torch.randperm(len(x), generator=torch.Generator().manual_seed(7))
    expected = 1 - grouped_ssim(x[order], y[order]).mean()
    torch.testing.assert_close(stochastic_ssim_loss(x, y, 1, torch.Generator().manual_seed(7)), expected)
    extra = torch.cat([x, torch.rand(5, 3, dtype=torch.float64)])
    value = stochastic_ssim_loss(extra, torch.cat([y, torch.rand(5, 3, dtype=torch.float64)]), 4, generator)
    assert 0 < float(value) < 1
    few = torch.rand(3, 3, requires_grad=True)
    small = stochastic_ssim_loss(few, torch.rand(3, 3), 2, generator)
    small.backward()
    assert float(small.detach()) == 0.0 and few.grad is not None


def test_groups_by_label_take_one_label_each():
    """With labels, a group holds rays of one label: two labels of 16 rays each, constant within a label, give
    SSIM's luminance term for each group alone (no contrast, whatever the order), by hand; a third label's 5 rays,
    less than a group, are left out. Without labels the groups mix the labels, and their contrasts count."""
    labels = torch.tensor([0, 1] * 16 + [2] * 5)[torch.randperm(37, generator=torch.Generator().manual_seed(1))]
    x = torch.tensor([0.2, 0.7, 0.0], dtype=torch.float64)[labels][:, None].expand(-1, 3)
    y = torch.tensor([0.3, 0.7, 1.0], dtype=torch.float64)[labels][:, None].expand(-1, 3)
    luminance = (2 * 0.2 * 0.3 + 1e-4) / (0.2**2 + 0.3**2 + 1e-4)
    expected = 1 - (luminance + 1) / 2
    value = stochastic_ssim_loss(x, y, 3, torch.Generator().manual_seed(2), labels)
    assert float(value) == pytest.approx(expected, rel=0, abs=1e-12)  # float64 sums of 16 terms
    mixed = stochastic_ssim_loss(x, y, 3, torch.Generator().manual_seed(2))
    assert abs(float(mixed) - expected) > 0.05


def test_the_term_composites_as_the_colour_loss_does():
    """structure_term renders over the data's background (white here) and weighs by train.s3im_weight; a render
    that matches its targets once composited costs nothing, the same render over black does."""
    config = FitConfig()
    config.train.s3im_weight = 0.5
    config.data.white_background = True
    n = 64
    generator = torch.Generator().manual_seed(3)
    mask = (torch.rand(n, generator=generator) > 0.5).float()
    colour = torch.rand(n, 3, generator=generator) * mask[:, None]
    target = colour + (1 - mask)[:, None]
    frames = torch.zeros(n, dtype=torch.long)
    batch = RayBatch(*(torch.zeros(n, 3),) * 2, frames, target, mask, torch.ones(n), frames)
    out = RenderOutput(colour, mask, torch.zeros(n))
    assert float(structure_term(config, out, batch, generator)) == pytest.approx(0.0, abs=1e-6)  # float32 sums
    config.data.white_background = False
    value = float(structure_term(config, out, batch, generator))
    expected = 0.5 * float(stochastic_ssim_loss(colour, target, 10, torch.Generator().manual_seed(0)))
    assert value > 0.1 and value == pytest.approx(expected, rel=0.2)  # other orderings: the same groups' spread


def test_the_option_is_for_subject_fits_that_render_rays():
    assert load_config("cpu", ["train.s3im_weight=0.2"]).train.s3im_weight == 0.2
    with pytest.raises(ConfigError, match="s3im_weight"):
        load_config("cpu", ["train.s3im_weight=-1"])
    with pytest.raises(ConfigError, match="s3im_repeats"):
        load_config("cpu", ["train.s3im_repeats=0"])
    assert load_config("cpu", ["train.s3im_groups=camera"]).train.s3im_groups == "camera"
    with pytest.raises(ConfigError, match="s3im_groups"):
        load_config("cpu", ["train.s3im_groups=image"])
    assert load_config("cpu_grid", ["train.s3im_weight=0.2"]).train.random_background  # beside random backgrounds


def test_the_term_over_random_backgrounds_leaves_the_band_out():
    """With random backgrounds the rays are composited over them and the targets outside the mask are those colours
    (as the colour term takes them); the band's rays (mask weight 0), whose targets keep the recording's colour, leave
    the groups: the term is the loss of the other rays alone, and a band ray's colour does not move it; grouped by
    camera, the kept rays' cameras label the groups."""
    config = FitConfig()
    config.train.s3im_weight = 0.5
    n = 80
    generator = torch.Generator().manual_seed(5)
    mask = (torch.rand(n, generator=generator) > 0.5).float()
    weight = torch.ones(n)
    weight[:16] = 0  # the band: 16 rays, so 64 kept, four whole groups
    backgrounds = torch.rand(n, 3, generator=generator)
    colour = torch.rand(n, 3, generator=generator) * mask[:, None]
    target = torch.rand(n, 3, generator=generator)
    frames = torch.zeros(n, dtype=torch.long)
    batch = RayBatch(*(torch.zeros(n, 3),) * 2, frames, target, mask, weight, frames)
    out = RenderOutput(colour, mask, torch.zeros(n))
    value = structure_term(config, out, batch, torch.Generator().manual_seed(9), backgrounds=backgrounds)
    kept = weight > 0
    rendered = (colour + (1 - mask)[:, None] * backgrounds)[kept]
    expected_target = torch.where(mask[:, None] > 0.5, target, backgrounds)[kept]
    expected = 0.5 * stochastic_ssim_loss(rendered, expected_target, 10, torch.Generator().manual_seed(9))
    torch.testing.assert_close(value, expected)  # the same orderings of the same 64 rays: the same sums
    batch.rgb[:16] = 1 - batch.rgb[:16]
    moved = structure_term(config, out, batch, torch.Generator().manual_seed(9), backgrounds=backgrounds)
    torch.testing.assert_close(moved, expected)
    config.train.s3im_groups, batch.cameras = "camera", torch.arange(n) % 2  # the kept rays' cameras label them
    by_camera = structure_term(config, out, batch, torch.Generator().manual_seed(9), backgrounds=backgrounds)
    labels = batch.cameras[kept]
    expected = 0.5 * stochastic_ssim_loss(rendered, expected_target, 10, torch.Generator().manual_seed(9), labels)
    torch.testing.assert_close(by_camera, expected)


@pytest.mark.parametrize("random_background", [False, True])
def test_a_step_adds_the_term_and_draws_nothing_without_it(data_root_64, tmp_path, random_background):
    """One training step on the same batch with and without train.s3im_weight, on the data's background and on random
    ones: the loss differs by the term (the step's losses are logged), and the term's random orders come from the
    fit's generator only when it is on."""
    from fitting.run_folder import prepare_run_dir
    from pipelines.runs.fit import start_run

    losses, states = [], []
    for weight in (0.0, 1.0):
        sets = [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=1", f"train.s3im_weight={weight}"]
        sets.append(f"train.random_background={random_background}")
        folder = prepare_run_dir(tmp_path / f"run{weight}", False)
        trainer = start_run(folder, torch.device("cpu"), load_config("tiny", sets), progress=False)
        losses.append(trainer.train_step()[0])
        states.append(trainer.generator.get_state())
    # 1 - S3IM of a field a step old lies well above 0.05 (SSIM of noise against the images)
    assert losses[1] > losses[0] + 0.05
    assert not torch.equal(states[0], states[1])


def test_the_fading_weight_falls_with_the_budget(data_root_64, tmp_path):
    """With train.s3im_fade the term's weight is train.s3im_weight x (1 - the budget's progress): halfway through the
    budget a step's loss lies halfway between the step without the term and the step with all of it (the same batch
    and orders: every trainer starts from the same seed). Tolerance: float32 sums of a few hundred rays' losses."""
    from fitting.run_folder import prepare_run_dir
    from pipelines.runs.fit import start_run

    losses = []
    for name, extra in (("off", ["train.s3im_weight=0"]), ("on", []), ("fade", ["train.s3im_fade=true"])):
        sets = [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=1", "train.s3im_weight=1", *extra]
        folder = prepare_run_dir(tmp_path / name, False)
        trainer = start_run(folder, torch.device("cpu"), load_config("tiny", sets), progress=False)
        trainer.budget._clock = 0.5  # half the budget's minutes spent
        losses.append(trainer.train_step()[0])
    assert losses[1] > losses[0] + 0.05
    assert losses[2] == pytest.approx((losses[0] + losses[1]) / 2, abs=1e-5)
