import json
import os
import signal
import subprocess
import sys
import time

import imageio.v2 as imageio
import numpy as np
import pytest
import spawn
import torch
from scipy import ndimage
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from fitting.checkpoint import CheckpointError, load_checkpoint
from fitting.config import ConfigError, load_config
from fitting.evaluate import average_metrics, frame_metrics, masked_blur
from fitting.run_folder import prepare_run_dir
from fitting.schedule import Budget, lr_factor
from pipelines.cli import eval as cli_eval
from pipelines.cli import fit as cli_fit
from pipelines.cli.common import run_cli
from pipelines.runs.fit import resume_run, start_run
from pipelines.runs.requests import EvalRequest, VideoRequest
from pipelines.runs.subject.evaluation import evaluate_run


def _config(root, *extra):
    return load_config("tiny", [f"data.data_root={root}", "data.ratio=1.0", *extra])


def _fit(root, out, *extra, resume=False):
    config = _config(root, *extra)
    run = prepare_run_dir(out, resume)
    if resume:
        return resume_run(run, torch.device("cpu"), progress=False)
    return start_run(run, torch.device("cpu"), config, progress=False)


def test_tiny_fit_loss_falls_and_eval_writes_every_artefact(data_root_64, tmp_path):
    trainer = _fit(data_root_64, tmp_path / "run", "train.steps=60", "train.validate_every=60")
    result = trainer.fit()
    assert result.finished and result.step == 60
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert np.mean([r["loss"] for r in log[-3:]]) < 0.7 * np.mean([r["loss"] for r in log[:2]])
    for name in ("config.yaml", "checkpoint.pt", "curve.png", "val/step_0000060.png"):
        assert (tmp_path / "run" / name).is_file(), name
    report = evaluate_run(
        tmp_path / "run", EvalRequest(("same_pose_novel_view", "novel_pose_novel_view"), 2, progress=False)
    )
    split = report["splits"]["novel_pose_novel_view"]
    assert split["n_views"] == 2 and set(split["full"]) == {"mask_l2", "psnr", "ssim"} and split["nb_crop"]
    assert report["versions"]["scikit-image"]
    assert report["samples"] == [8, 8]  # the tiny preset's evaluation counts, named with the figures
    assert set(split["nb_crop"]["breakdown"]) >= {"share_person", "share_silhouette", "share_band", "psnr_person"}
    assert sum(
        split["nb_crop"]["breakdown"][f"pixels_{k}"] for k in ("person", "silhouette", "band", "background")
    ) == (
        pytest.approx(1.0)  # every pixel of R in one class; mean of two sums of float64 fractions
    )
    markdown = (tmp_path / "run" / "eval" / "metrics.md").read_text()
    assert markdown.count("|") > 10 and "NN: person pixels" in markdown
    assert markdown.startswith("# narf_d (width 16, 8 + 8 samples a ray), step 60:")
    assert "surfaces no training view saw face-on" in markdown  # the tiny capture's held-out cameras see some of them
    assert 0.0 <= split["nb_crop"]["breakdown"]["pixels_unseen"] <= 1.0
    assert len(list((tmp_path / "run" / "eval" / "grids").rglob("*.png"))) == 4


def test_resume_equals_uninterrupted(data_root_64, tmp_path):
    straight = _fit(data_root_64, tmp_path / "a", "train.steps=12")
    straight.fit()
    first = _fit(data_root_64, tmp_path / "b", "train.steps=12")
    for _ in range(5):
        first.train_step()
    first.checkpoint()
    del first  # "killed" right after its checkpoint
    resumed = _fit(data_root_64, tmp_path / "b", "train.steps=12", resume=True)
    assert resumed.step == 5
    resumed.fit()
    a, b = load_checkpoint(tmp_path / "a"), load_checkpoint(tmp_path / "b")
    assert b["step"] == a["step"] == 12
    for key, value in a["model"].items():
        # the resumed run replays the same batches and jitter; only the order of float32 reductions may differ
        # between runs (thread scheduling), ~eps32 per step on weights ~1 over 7 steps, well below 1e-6
        assert torch.allclose(value, b["model"][key], atol=1e-6), key


def test_fit_killed_with_sigkill_resumes_to_the_end(data_root_64, tmp_path):
    out = tmp_path / "run"
    command = [
        sys.executable,
        "-c",
        "from pipelines.cli.fit import entrypoint; entrypoint()",
        "--config",
        "tiny",
        "--data-root",
        str(data_root_64),
        "--out",
        str(out),
        "--quiet",
        "--set",
        "data.ratio=1.0",
        "--set",
        "train.steps=400",
        "--set",
        "train.checkpoint_minutes=0",
    ]
    process = spawn.popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and not (out / "checkpoint.pt").exists():
        time.sleep(0.2)
    time.sleep(1.0)
    os.kill(process.pid, signal.SIGKILL)
    spawn.finish(process, 30, "narf-fit after SIGKILL")
    killed_at = load_checkpoint(out)["step"]  # the visible checkpoint is always a complete one
    assert 0 < killed_at < 400
    with open(out / "log.jsonl", "a") as log:  # rows past the checkpoint, the last one cut short, as a kill leaves
        log.write(json.dumps({"step": killed_at + 5, "loss": 1.0}) + "\n" + '{"step": ' + str(killed_at + 10))
    done = spawn.run(command[:3] + ["--out", str(out), "--resume", "--quiet"], 300, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert load_checkpoint(out)["step"] == 400
    assert not list(out.glob(".checkpoint.*"))  # a temporary left by the kill is cleaned by the next save
    steps = [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()]
    assert steps == sorted(set(steps)) and steps[-1] == 400, steps  # each step once, in order


def test_crop_error_breakdown_by_hand():
    """Eight pixels of R, one class each (docs/model.md §7): person (0,0) (1,0), silhouette (0,1), band (0,2)
    (1,1), background (0,3) (1,2) (1,3); the colour differences are 0.1, 0.2, 0.3, 0, 0.1, 0.4, 0, 0.05 in every
    channel, so the squared errors are 0.01, 0.04, 0.09, 0, 0.01, 0.16, 0, 0.0025 (sum 0.3125). R sits in a 12 x 12
    image (SSIM's window) whose other pixels carry error that the breakdown must ignore."""

    def image(block: np.ndarray, fill) -> np.ndarray:
        out = np.full((12, 12, *block.shape[2:]), fill, block.dtype)
        out[3:5, 4:8] = block
        return out

    gt_mask = image(np.array([[1, 1, 0, 0], [1, 0, 0, 0]], float), 1.0)
    band = image(np.array([[0, 0, 1, 0], [0, 1, 0, 0]], bool), True)
    opacity = image(np.array([[0.9, 0.2, 0.7, 0.0], [0.5, 0.8, 0.49, 0.0]]), 0.0)
    gt = np.full((12, 12, 3), 0.5)
    pred = image(0.5 + np.array([[0.1, 0.2, 0.3, 0.0], [0.1, 0.4, 0.0, 0.05]])[..., None].repeat(3, -1), 0.0)
    region = image(np.ones((2, 4), bool), False)
    b = frame_metrics({"rgb": pred, "mask": opacity}, gt, gt_mask, region, 0.0, band)["nb_crop"]["breakdown"]
    # float64 sums of eight terms: exact to ~1e-16 relative, pytest.approx's default rtol 1e-6 is ample
    assert b["share_person"] == pytest.approx(0.02 / 0.3125)
    assert b["share_silhouette"] == pytest.approx(0.04 / 0.3125)
    assert b["share_band"] == pytest.approx(0.25 / 0.3125)
    assert b["share_background"] == pytest.approx(0.0025 / 0.3125)
    assert [b[f"pixels_{k}"] for k in ("person", "silhouette", "band", "background")] == [0.25, 0.125, 0.25, 0.375]
    assert b["psnr_person"] == pytest.approx(20.0)  # MSE 0.01 over the two person pixels
    assert b["psnr_band_bound"] == pytest.approx(10 * np.log10(8 / 0.25))  # the band's 0.25 alone over R's 8 pixels
    # a view without person pixels: its psnr_person is None and left out of the mean, its shares are not
    no_one = np.zeros((12, 12))
    empty = frame_metrics({"rgb": pred, "mask": no_one}, gt, no_one, region, 0.0, band)["nb_crop"]
    assert empty["breakdown"]["psnr_person"] is None
    mean = average_metrics(
        [{"nb_crop": empty}, {"nb_crop": {"mask_l2": 0, "psnr": 0, "ssim": 0, "breakdown": b}}], "nb_crop"
    )
    assert mean["breakdown"]["psnr_person"] == pytest.approx(20.0)
    assert mean["breakdown"]["pixels_band"] == pytest.approx(0.25)  # the band is the same in both views


def test_the_unseen_surfaces_split_the_person_pixels_by_hand():
    """Four opaque person pixels with colour errors 0.1, 0.2, 0.3 and 0.4 in every channel (squared 0.01, 0.04, 0.09,
    0.16; sum 0.3): the last two show a surface no training view saw, so they are half the person pixels and 0.25 /
    0.3 of their error, the PSNR elsewhere that of MSE 0.025 and there of MSE 0.125; pixels outside the person do not
    count, even when marked (float64 sums of four terms: pytest.approx's default rtol 1e-6 is ample)."""
    mask = np.zeros((12, 12))
    mask[4, 4:8] = 1.0
    truth = np.zeros((12, 12, 3))
    pred = truth.copy()
    pred[4, 4:8] = np.array([0.1, 0.2, 0.3, 0.4])[:, None]
    unseen = np.zeros((12, 12), bool)
    unseen[4, 6:8] = unseen[8, 8] = True
    b = frame_metrics({"rgb": pred, "mask": mask}, truth, mask, np.ones((12, 12), bool), 0.0, mask < 0, unseen)
    b = b["nb_crop"]["breakdown"]
    assert b["pixels_unseen"] == 0.5
    assert b["share_unseen"] == pytest.approx(0.25 / 0.3)
    assert b["psnr_person_seen"] == pytest.approx(-10 * np.log10(0.025))
    assert b["psnr_person_unseen"] == pytest.approx(-10 * np.log10(0.125))
    everything_seen = frame_metrics({"rgb": pred, "mask": mask}, truth, mask, mask > 0, 0.0, mask < 0, unseen < 0)
    b = everything_seen["nb_crop"]["breakdown"]
    assert b["pixels_unseen"] == 0.0 and b["psnr_person_unseen"] is None
    assert b["psnr_person_seen"] == pytest.approx(b["psnr_person"])


def test_the_inner_person_pixels_lie_three_pixels_inside_the_mask():
    """A 10 x 10 person in a 14 x 14 image, rendered opaque, the colour off by 0.1 on its central 4 x 4 pixels (3 px
    or more inside its edge) and by 0.3 on the 84 others: psnr_person_inner is 20 dB (MSE 0.01), psnr_person that of
    MSE (16 * 0.01 + 84 * 0.09) / 100 (float64 sums of 100 terms: pytest.approx's default rtol 1e-6 is ample)."""
    mask = np.zeros((14, 14))
    mask[2:12, 2:12] = 1.0
    pred = np.zeros((14, 14, 3))
    pred[2:12, 2:12] = 0.3
    pred[5:9, 5:9] = 0.1
    b = frame_metrics({"rgb": pred, "mask": mask}, np.zeros((14, 14, 3)), mask, mask > 0, 0.0, mask < 0)
    b = b["nb_crop"]["breakdown"]
    assert b["psnr_person_inner"] == pytest.approx(20.0)
    assert b["psnr_person"] == pytest.approx(-10 * np.log10((16 * 0.01 + 84 * 0.09) / 100))


def test_the_coarse_person_psnr_keeps_the_colour_and_drops_the_detail():
    """A 40 x 40 opaque person in a 60 x 60 image: rendered 0.1 too bright, psnr_person_coarse equals psnr_person,
    20 dB (a constant stays itself under the normalised blur; float64); rendered with a 1-px checkerboard of +-0.1,
    psnr_person is 20 dB and the coarse PSNR far higher (the checkerboard's frequency is damped by exp(-2 pi^2
    sigma^2 / 4) = e^-79 at sigma 4 px; what is left comes from the blur's one-sided weights near the edge)."""
    mask = np.zeros((60, 60))
    mask[10:50, 10:50] = 1.0
    truth = np.zeros((60, 60, 3))
    truth[10:50, 10:50] = np.linspace(0.2, 0.6, 40)[:, None, None]  # shading down the body
    checker = 0.1 * (-1.0) ** np.add.outer(np.arange(60), np.arange(60))[..., None]
    for pred, coarse in ((truth + 0.1 * mask[..., None], 20.0), (truth + checker * mask[..., None], None)):
        b = frame_metrics({"rgb": pred, "mask": mask}, truth, mask, mask > 0, 0.0, mask < 0)["nb_crop"]["breakdown"]
        assert b["psnr_person"] == pytest.approx(20.0)
        if coarse is None:
            assert b["psnr_person_coarse"] > 40.0
        else:
            assert b["psnr_person_coarse"] == pytest.approx(coarse)


def test_the_gain_person_psnr_takes_away_what_a_channel_gain_explains():
    """A 20 x 20 opaque person: rendered at 1.25 / 0.8 / 1.1 times the image's colour, psnr_person_gain is at the
    PSNR's floor (MSE clamped at 1e-12: float64 residuals of 1e-16); rendered as a constant 0.4 plus a 1-px
    checkerboard of +-0.1, the best gain is 0.16 / 0.17 and the MSE left is 0.16 (1 - 0.16 / 0.17), by hand
    (float64 sums of 400 terms: pytest.approx's default rtol 1e-6 is ample)."""
    mask = np.zeros((30, 30))
    mask[5:25, 5:25] = 1.0
    gen = np.random.default_rng(3)
    truth = gen.uniform(0.2, 0.8, (30, 30, 3)) * mask[..., None]
    scaled = truth * np.array([1.25, 0.8, 1.1])
    b = frame_metrics({"rgb": scaled, "mask": mask}, truth, mask, mask > 0, 0.0, mask < 0)["nb_crop"]["breakdown"]
    assert b["psnr_person"] < 30.0
    assert b["psnr_person_gain"] == pytest.approx(120.0)
    flat = 0.4 * mask[..., None] * np.ones(3)
    checker = 0.1 * (-1.0) ** np.add.outer(np.arange(30), np.arange(30))[..., None] * mask[..., None]
    b = frame_metrics({"rgb": flat + checker, "mask": mask}, flat, mask, mask > 0, 0.0, mask < 0)
    b = b["nb_crop"]["breakdown"]
    assert b["psnr_person"] == pytest.approx(20.0)
    assert b["psnr_person_gain"] == pytest.approx(-10 * np.log10(0.16 * (1 - 0.16 / 0.17)))


def test_the_masked_blur_against_scipy():
    """masked_blur is scipy's Gaussian filter of I 1_P over that of 1_P, both zero outside the image: OpenCV and
    scipy both truncate the kernel at 4 sigma (33 taps at sigma 4); float64 sums of 33^2 terms."""
    gen = np.random.default_rng(2)
    image, where = gen.random((30, 40, 3)), gen.random((30, 40)) > 0.3
    got = masked_blur(image, where, 4.0)
    weight = where.astype(np.float64)
    num = np.stack([ndimage.gaussian_filter(image[..., c] * weight, 4.0, mode="constant") for c in range(3)], -1)
    want = num / ndimage.gaussian_filter(weight, 4.0, mode="constant")[..., None]
    np.testing.assert_allclose(got[where], want[where], rtol=1e-9)


def test_metrics_against_scikit_image():
    gen = np.random.default_rng(0)
    gt = gen.random((32, 40, 3))
    pred = np.clip(gt + gen.normal(0, 0.05, gt.shape), 0, 1)
    gt_mask = (gen.random((32, 40)) > 0.5).astype(float)
    mask = np.clip(gt_mask + gen.normal(0, 0.1, gt_mask.shape), 0, 1)
    region = np.zeros((32, 40), bool)
    region[5:20, 8:30] = True
    region[6, 8] = False
    m = frame_metrics({"rgb": pred, "mask": mask}, gt, gt_mask, region, 0.0)
    # float64 throughout and the same formulas as the references: PSNR to 1e-6 dB (rounding ~1e-13); the rest
    # with pytest.approx's default rtol 1e-6 (different summation order of a few thousand float64 terms: ~1e-13)
    assert m["full"]["psnr"] == pytest.approx(peak_signal_noise_ratio(gt, pred, data_range=1.0), abs=1e-6)
    assert m["full"]["ssim"] == pytest.approx(
        structural_similarity(
            pred, gt, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1
        )
    )
    assert m["full"]["mask_l2"] == pytest.approx(1e4 * np.mean((mask - gt_mask) ** 2))
    mse_region = np.mean((pred[region] - gt[region]) ** 2)
    assert m["nb_crop"]["psnr"] == pytest.approx(10 * np.log10(1 / mse_region), abs=1e-6)
    assert m["nb_crop"]["mask_l2"] == pytest.approx(1e4 * np.mean((mask[region] - gt_mask[region]) ** 2))
    p, g = pred.copy(), gt.copy()
    p[~region], g[~region] = 0, 0
    ref = structural_similarity(
        p[5:20, 8:30],
        g[5:20, 8:30],
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        channel_axis=-1,
    )
    assert m["nb_crop"]["ssim"] == pytest.approx(ref)


def test_video_decodes_to_expected_frames(data_root_64, tmp_path):
    from pipelines.runs.subject.video import render_video

    _fit(data_root_64, tmp_path / "run", "train.steps=2").fit()
    for kind in ("orbit", "poses", "bones"):
        path = render_video(
            tmp_path / "run", VideoRequest(kind, tmp_path / f"{kind}.mp4", frames=5, fps=10, progress=False)
        )
        reader = imageio.get_reader(path)
        frames = [f for f in reader]
        expected = 1 if kind == "poses" else 5  # 10 frames: one held-out pose
        assert len(frames) == expected and frames[0].shape == (64, 64 * 3, 3), kind


def test_config_is_strict():
    with pytest.raises(ConfigError, match="unknown config key 'train.foo'"):
        load_config("tiny", ["train.foo=1"])
    with pytest.raises(ConfigError, match="'train.steps': expected an integer"):
        load_config("tiny", ["train.steps=1.5"])
    with pytest.raises(ConfigError, match="unknown preset 'fast'"):
        load_config("fast")
    with pytest.raises(ConfigError, match="render.grid_proposal: the proposal is the occupancy grid's density"):
        load_config("tiny", ["render.grid_proposal=true", "render.occupancy=false"])
    assert load_config("cpu", ["model.width=32"]).model.width == 32
    from fitting.config import CONFIG_DIR

    for preset in sorted(CONFIG_DIR.glob("*.yaml")):  # every shipped preset loads strictly and validates
        load_config(preset.stem)


class TestBadInput:
    def test_missing_and_corrupt_checkpoint(self, tmp_path, capsys):
        (tmp_path / "run").mkdir()
        assert run_cli("narf-eval", cli_eval.main, ["--run", str(tmp_path / "run")]) == 2
        assert "no checkpoint" in capsys.readouterr().err
        (tmp_path / "run" / "checkpoint.pt").write_bytes(b"\x80\x02garbage")
        with pytest.raises(CheckpointError, match="corrupt or unreadable checkpoint"):
            load_checkpoint(tmp_path / "run")
        assert run_cli("narf-eval", cli_eval.main, ["--run", str(tmp_path / "nope")]) == 2

    def test_fit_errors(self, tmp_path, data_root_64, capsys):
        assert (
            run_cli(
                "narf-fit", cli_fit.main, ["--config", "tiny", "--set", "train.bogus=1", "--out", str(tmp_path / "x")]
            )
            == 2
        )
        assert "unknown config key 'train.bogus'" in capsys.readouterr().err
        assert (
            run_cli(
                "narf-fit",
                cli_fit.main,
                ["--config", "tiny", "--subject", "kick", "--data-root", str(tmp_path), "--out", str(tmp_path / "y")],
            )
            == 2
        )
        assert "no subject 'kick'" in capsys.readouterr().err
        (tmp_path / "file").write_text("")
        assert (
            run_cli(
                "narf-fit",
                cli_fit.main,
                ["--config", "tiny", "--data-root", str(data_root_64), "--out", str(tmp_path / "file")],
            )
            == 2
        )
        assert "exists and is a file" in capsys.readouterr().err
        assert not list(tmp_path.glob("x/checkpoint.pt"))

    def test_split_the_capture_lacks(self, tmp_path):
        from pipelines.synthetic.capture import SynthConfig, generate_capture

        root = tmp_path / "root"
        generate_capture(
            root / "synthetic" / "taichi",
            SynthConfig(resolution=48, frames=1, cameras=2, calib_shots=0, workers=1),
            progress=False,
        )
        _fit(root, tmp_path / "run", "train.steps=1").fit()
        with pytest.raises(ValueError, match="split 'novel_pose' is empty"):
            evaluate_run(tmp_path / "run", EvalRequest(("novel_pose",), progress=False))


def test_learning_rate_decays_to_its_floor(data_root_64, tmp_path):
    trainer = _fit(
        data_root_64,
        tmp_path / "run",
        "train.steps=10",
        "train.log_every=1",
        "train.lr_decay=0.5",
        "train.lr_min=0.001",
    )
    trainer.fit()
    rates = [json.loads(line)["lr"] for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    # the learning rates are float64 products of 0.01 and 0.5, rounded once when logged: approx's rtol 1e-6
    assert rates[0] == pytest.approx(0.005) and rates[-1] == pytest.approx(0.001) and min(rates) >= 0.001 - 1e-12
    with pytest.raises(ConfigError, match="train.lr_min"):
        load_config("tiny", ["train.lr_min=0.5"])


def test_learning_rate_anneals_over_the_end_of_the_budget(data_root_64, tmp_path):
    # 10 steps, the last 40 % annealed to 0.1: the factor is 1 through step 6, then 0.1^((k/10 - 0.6) / 0.4)
    assert lr_factor(6, 0.6, 1.0, 0.0, 0.4, 0.1) == 1.0
    assert lr_factor(8, 0.8, 1.0, 0.0, 0.4, 0.1) == pytest.approx(0.1**0.5, rel=1e-12)
    assert lr_factor(3, 1.0, 0.5, 0.0, 0.4, 0.1) == pytest.approx(0.125 * 0.1, rel=1e-12)
    assert lr_factor(3, 1.0, 0.5, 0.0, 0.0, 0.1) == 0.125  # off: upstream's decay alone
    budget = Budget(steps=100, minutes=1.0)
    budget.tick(lambda fraction: 0.75)  # the clock as agreed between processes
    assert budget.progress(10) == 0.75 and not budget.out_of_time
    budget.tick(lambda fraction: 1.0)
    assert budget.out_of_time and budget.progress(10) == 1.0
    trainer = _fit(data_root_64, tmp_path / "run", "train.steps=10", "train.log_every=1", "train.lr_anneal=0.4")
    trainer.fit()
    rates = [json.loads(line)["lr"] for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    # logged after each step k = 1..10: 0.01 · 0.99995^k · a(k / 10), float64 rounded once when logged
    expected = [0.01 * 0.99995**k * 0.1 ** max((k / 10 - 0.6) / 0.4, 0.0) for k in range(1, 11)]
    assert rates == pytest.approx(expected, rel=1e-9)
    for bad in ("train.lr_anneal=1.5", "train.lr_anneal_to=0"):
        with pytest.raises(ConfigError, match=bad.split("=")[0]):
            load_config("tiny", [bad])


def test_adam_beta2_sets_the_squared_gradients_decay(data_root_64, tmp_path):
    """After one step Adam's second moment is (1 - beta2) g^2 (torch.optim.Adam, from zero): the config's beta2
    reaches the optimiser; a value outside (0, 1) is refused."""
    trainer = _fit(data_root_64, tmp_path / "run", "train.steps=1", "train.adam_beta2=0.99")
    trainer.train_step()
    trained = [p for group in trainer.optimiser.param_groups for p in group["params"] if p.grad is not None]
    assert trained
    for parameter in trained:
        # one float32 multiply each side: a relative error of a few ulps
        expected = 0.01 * parameter.grad.square()
        torch.testing.assert_close(trainer.optimiser.state[parameter]["exp_avg_sq"], expected, rtol=1e-5, atol=0)
    with pytest.raises(ConfigError, match="train.adam_beta2"):
        load_config("tiny", ["train.adam_beta2=1"])


def test_save_checkpoint_removes_stale_temporaries(tmp_path):
    from fitting.checkpoint import save_checkpoint

    (tmp_path / ".checkpoint.dead.tmp").write_bytes(b"half a checkpoint")
    save_checkpoint(tmp_path, {"config": {}, "step": 3, "model": {}})
    assert not list(tmp_path.glob(".checkpoint.*")) and load_checkpoint(tmp_path)["step"] == 3


def test_precision_and_compile_switches(data_root_64, tmp_path):
    """bf16 autocast trains (finite loss, close to fp32 after the same steps); compile wraps the field's forward
    without changing its state_dict keys (compiling itself takes minutes on a CPU and is measured in the bench)."""
    losses = {}
    for precision in ("fp32", "bf16"):
        trainer = _fit(data_root_64, tmp_path / precision, "train.steps=3", f"train.precision={precision}")
        losses[precision] = [trainer.train_step()[0] for _ in range(3)]
    assert all(np.isfinite(losses["bf16"]))
    # bf16 keeps 8 significant bits (relative 2^-8 = 0.4 % per rounding) through ~20 layers: a few % on the loss
    assert np.allclose(losses["bf16"], losses["fp32"], rtol=0.1)
    eager = _fit(data_root_64, tmp_path / "eager", "train.steps=1").field.state_dict().keys()
    compiled = _fit(data_root_64, tmp_path / "compiled", "train.steps=1", "train.compile=true").field
    assert compiled.state_dict().keys() == eager and hasattr(compiled.forward, "_torchdynamo_orig_callable")
    with pytest.raises(ConfigError, match="train.precision"):
        _config(data_root_64, "train.precision=fp16")
    with pytest.raises(ConfigError, match="render.occupancy"):  # the grid is per subject, not across people
        load_config("ae_tiny", ["render.occupancy=true"])
    with pytest.raises(ConfigError, match="render.occupancy_resolution"):
        _config(data_root_64, "render.occupancy_resolution=1")


_SUBNORMAL_PROBE = """
import sys, torch
def probe():  # 2**20 copies of the smallest subnormal, doubled on 2 threads: a thread that flushes writes 0
    tiny = torch.ones(1 << 20, dtype=torch.int32).view(torch.float32)
    return int(((tiny * 2).view(torch.int32) != 0).sum())
torch.set_num_threads(2)
if sys.argv[1] == "late":  # the worker threads start before the mode is set
    probe(); print(torch.set_flush_denormal(True), probe())
else:
    import pipelines.cli.fit as fit  # every import a command makes before it runs
    fit.run_cli("probe", lambda argv: print(torch.set_flush_denormal(True), probe()))
"""


@pytest.mark.parametrize("order", ["cli", "late"])
def test_subnormals_flushed_in_every_thread(order):
    """flush_subnormals (set by run_cli before a command's work) reaches both CPU threads: the doubled subnormals all
    come back exactly 0 (integer count). Set after the worker threads started, the worker keeps its own half, which the
    probe sees; that second case shows the probe can fail. Skipped where torch has no flush mode for this CPU."""
    done = spawn.run([sys.executable, "-c", _SUBNORMAL_PROBE, order], 60, capture_output=True, text=True, check=True)
    supported, unflushed = done.stdout.split()
    if supported != "True":
        pytest.skip("torch has no flush-to-zero mode on this CPU")
    assert (int(unflushed) == 0) == (order == "cli")


@pytest.mark.parametrize("user_env", [{}, {"MALLOC_MMAP_THRESHOLD_": "131072"}])
def test_allocator_keeps_freed_memory_unless_the_user_chose(user_env):
    """keep_freed_memory: glibc's mallopt accepts both thresholds (it returns 0 for a value out of its range, e.g. an
    mmap threshold above 32 MiB); a user's own malloc settings are left alone."""
    import platform

    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "LD_PRELOAD"} | user_env
    code = "from pipelines.cli.common import keep_freed_memory; print(keep_freed_memory())"
    done = spawn.run([sys.executable, "-c", code], 60, capture_output=True, text=True, env=env, check=True)
    expected = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc" and not user_env
    assert done.stdout.strip() == str(expected)


_SPIN_PROBE = """
from pipelines.cli.common import run_cli

run_cli("probe", lambda argv: None, [])  # run_cli's flush imports torch, which loads libgomp
import os, sys
print("after:", os.environ.get("GOMP_SPINCOUNT"), file=sys.stderr)
"""


@pytest.mark.parametrize("user_env", [{}, {"OMP_WAIT_POLICY": "ACTIVE"}, {"GOMP_SPINCOUNT": "2000"}])
def test_openmp_workers_sleep_sooner_unless_the_user_chose(user_env):
    """short_openmp_wait (set by run_cli before torch is imported) reaches libgomp: the runtime's own report of its
    settings (OMP_DISPLAY_ENV, printed when torch loads it) reads 10000 spins; a user's OMP_WAIT_POLICY or
    GOMP_SPINCOUNT is left as they set it. Skipped where torch's OpenMP runtime is not libgomp (it prints no
    GOMP_SPINCOUNT)."""
    env = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    env |= {"OMP_DISPLAY_ENV": "VERBOSE", **user_env}
    done = spawn.run([sys.executable, "-c", _SPIN_PROBE], 60, capture_output=True, text=True, env=env, check=True)
    spins = [line.split("=")[1].strip(" '") for line in done.stderr.splitlines() if "GOMP_SPINCOUNT" in line]
    if not spins:
        pytest.skip("torch's OpenMP runtime is not libgomp")
    expected = {"OMP_WAIT_POLICY": "30000000000", "GOMP_SPINCOUNT": "2000"}.get(next(iter(user_env), ""), "10000")
    assert spins == [expected]
    # the caller's environment as it was: the variable gone after the command, or the user's own kept
    assert f"after: {user_env.get('GOMP_SPINCOUNT')}" in done.stderr.splitlines()


def test_every_command_loads_without_torch():
    """The OpenMP wait is set by run_cli before torch loads libgomp, so no command's module may import torch at
    load. (Checked against narf-cost importing narf.fields at load: the test fails.)"""
    import tomllib
    from pathlib import Path

    scripts = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]["scripts"]
    modules = sorted({target.split(":")[0] for target in scripts.values()})
    probe = "import importlib, sys\nfor m in sys.argv[1:]:\n    importlib.import_module(m)\n    assert 'torch' not in sys.modules, m"  # noqa: E501
    done = spawn.run([sys.executable, "-c", probe, *modules], 120, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr.strip().splitlines()[-1]


def test_eval_takes_several_splits(tiny_run, tmp_path, capsys):
    """--split repeats: every named split is evaluated once, in the order given ('all' expands in place); one wrong
    name fails the whole call before anything is rendered. (A copy of the shared run: its report accumulates the
    splits other tests evaluate.)"""
    import shutil

    shutil.copytree(tiny_run, tmp_path / "run")
    tiny_run = tmp_path / "run"
    shutil.rmtree(tiny_run / "eval", ignore_errors=True)
    argv = ["--run", str(tiny_run), "--limit", "1", "--grids", "0", "--quiet"]
    twice = ["--split", "novel_pose_novel_view", "--split", "same_pose_novel_view", "--split", "novel_pose_novel_view"]
    assert run_cli("narf-eval", cli_eval.main, [*argv, *twice]) == 0
    report = json.loads((tiny_run / "eval" / "metrics.json").read_text())
    assert list(report["splits"]) == ["novel_pose_novel_view", "same_pose_novel_view"]
    assert run_cli("narf-eval", cli_eval.main, [*argv, "--split", "novel_pose", "--split", "cross_dataset"]) == 2
    assert "a subject run; 'cross_dataset' is not one of its splits" in capsys.readouterr().err


def test_a_diverging_fit_stops_with_its_last_good_checkpoint(data_root_64, tmp_path, capsys, monkeypatch):
    """A NaN loss at step 4 ends the fit with one line naming the step (exit 2), never 'finished'; the checkpoint
    of step 3 (written every step here) stays, with finite weights."""
    import math

    from fitting.trainer import Trainer

    real = Trainer.train_step

    def poisoned(self):
        loss, score = real(self)
        return (math.nan, score) if self.step == 4 else (loss, score)

    monkeypatch.setattr(Trainer, "train_step", poisoned)
    out = tmp_path / "run"
    argv = ["--config", "tiny", "--data-root", str(data_root_64), "--out", str(out), "--quiet"]
    argv += ["--set", "data.ratio=1.0", "--set", "train.steps=10", "--set", "train.checkpoint_minutes=0"]
    assert run_cli("narf-fit", cli_fit.main, argv) == 2
    captured = capsys.readouterr()
    last = captured.err.strip().splitlines()[-1]  # (after the data notice and the fit's banner)
    assert last.startswith("narf-fit: error: ") and "the training loss became nan at step 4" in last
    assert "kept the checkpoint of step 3" in last and "finished" not in captured.out
    state = load_checkpoint(out)
    assert state["step"] == 3 and all(torch.isfinite(v).all() for v in state["model"].values())


def test_resume_and_budget_flags_are_checked(tiny_run, capsys):
    """--resume may lengthen a run, not end it before where it stands; --max-minutes is a finite number > 0."""
    argv = ["--out", str(tiny_run), "--resume", "--set", "train.steps=1"]
    assert run_cli("narf-fit", cli_fit.main, argv) == 2
    assert "the run is at step 2; --set train.steps=1 would end it before where it stands" in capsys.readouterr().err
    for bad in ("-1", "0", "nan", "inf", "soon"):
        with pytest.raises(SystemExit) as exit_info:
            cli_fit.main(["--out", str(tiny_run), "--resume", "--max-minutes", bad])
        assert exit_info.value.code == 2 and "--max-minutes: expected" in capsys.readouterr().err
