"""The autoencoder across people: poses from joint frames, a tiny fit on a tiny THUman-like set (resumable, and
learning), its evaluation splits including the SURREAL transfer, and the errors for mixed-up runs."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from fitting.autoencoder import colour_gains, encode, refine_code
from fitting.checkpoint import load_checkpoint
from fitting.cnn_trainer import CnnAutoencoderTrainer
from fitting.config import ConfigError, load_config
from fitting.run_folder import prepare_run_dir
from narf.fields.cnn import POSE_DIM
from narf.fields.encoder import ImageEncoder
from pipelines.body.model import pose_batch, pose_batch_from_joints
from pipelines.cli import eval as cli_eval
from pipelines.cli import fit as cli_fit
from pipelines.cli.common import run_cli
from pipelines.datasets.surreal import check_clip
from pipelines.runs.autoencoder.evaluation import evaluate_autoencoder_run, surreal_view
from pipelines.runs.fit import resume_run, start_run
from pipelines.runs.requests import EvalRequest
from pipelines.synthetic.surreal import SurrealSynthConfig, generate_surreal
from pipelines.synthetic.thuman import ThumanSynthConfig, generate_thuman


@pytest.fixture(scope="module")
def sets(tmp_path_factory):
    root = tmp_path_factory.mktemp("ae_data")
    thuman = ThumanSynthConfig(people=4, train_poses=2, novel_poses=1, renders_per_mesh=2, raw_items=0, seed=3)
    generate_thuman(root / "thuman", thuman, progress=False)
    generate_surreal(root / "synthetic" / "surreal", SurrealSynthConfig(clips=2, frames=4, seed=4), progress=False)
    return root


def _config(sets, *overrides):
    return load_config("ae_tiny", [f"data.data_root={sets / 'thuman'}", *overrides])


def test_pose_batch_from_joint_frames_matches_the_body_model(body_model64):
    gen = torch.Generator().manual_seed(0)
    poses, shapes = torch.randn(3, 72, generator=gen, dtype=torch.float64) * 0.3, torch.randn(3, 10, generator=gen)
    body = body_model64.pose_zju(poses, torch.randn(3, 3, generator=gen), torch.randn(3, 3, generator=gen), shapes)
    a, b = pose_batch(body), pose_batch_from_joints(body.world_from_joint)
    for key in ("world_from_part", "reach", "bone_lengths", "pose_features"):
        assert torch.equal(getattr(a, key), getattr(b, key)), key
    # the rest skeleton is recovered through R^T of smplx's rotations, which are orthonormal only to ~1e-8 (its
    # Rodrigues divides the axis by |theta + 1e-8|): offsets ~1 m carry errors ~1e-8 m
    assert torch.allclose(a.rest_offsets, b.rest_offsets, atol=1e-7)


def test_colour_jitter_gains_scale_the_encoder_input():
    gen = torch.Generator().manual_seed(0)
    gains = colour_gains(400, 0.3, gen)
    assert gains.shape == (400, 3) and gains.min() >= 0.7 and gains.max() <= 1.3 and gains.std() > 0.1
    assert colour_gains(4, 0.0, gen) is None
    encoder = ImageEncoder(8, image_size=128, base_channels=2).eval()
    dark = torch.randint(0, 100, (2, 3, 128, 128), dtype=torch.uint8, generator=gen)
    with torch.no_grad():
        assert torch.equal(encode(encoder, dark, torch.ones(2, 3)), encode(encoder, dark))
        # doubling values <= 99 stays below 255 and below the clamp, and float scaling by 2 commutes with
        # rounding (x / 255 * 2 == 2 x / 255 exactly), so the code equals that of the doubled image bit for bit
        doubled = encode(encoder, dark * 2)
        assert torch.equal(encode(encoder, dark, torch.full((2, 3), 2.0)), doubled)


def test_fit_learns_and_resumes_exactly(sets, tmp_path):
    # with colour jitter on, so that its draws are shown to replay from the checkpointed generator too
    config = _config(sets, "train.steps=16", "train.colour_jitter=0.3")
    straight = start_run(prepare_run_dir(tmp_path / "a", False), "cpu", config, progress=False)
    straight.fit()
    first = start_run(prepare_run_dir(tmp_path / "b", False), "cpu", config, progress=False)
    for _ in range(6):
        first.train_step()
    first.checkpoint()
    resumed = resume_run(tmp_path / "b", "cpu", progress=False)
    assert resumed.step == 6
    resumed.fit()
    a, b = load_checkpoint(tmp_path / "a"), load_checkpoint(tmp_path / "b")
    assert a["config"]["kind"] == b["config"]["kind"] == "autoencoder" and b["step"] == 16
    for part in ("model", "encoder"):
        for key, value in a[part].items():
            # float32 replay of the same batches (see test_fitting): only reduction order may differ, << 1e-6
            assert torch.allclose(value.float(), b[part][key].float(), atol=1e-6), (part, key)


def test_longer_fit_lowers_the_loss(sets, tmp_path):
    config = _config(sets, "train.steps=200", "train.log_every=20", "train.rays_per_image=64")
    trainer = start_run(prepare_run_dir(tmp_path / "run", False), "cpu", config, progress=False)
    trainer.fit()
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert np.mean([r["loss"] for r in log[-3:]]) < 0.7 * np.mean([r["loss"] for r in log[:2]])


def test_evaluation_splits_and_grids(sets, tmp_path, monkeypatch):
    monkeypatch.setenv("NARF_DATA", str(sets))
    config = _config(sets, "train.steps=4")
    start_run(prepare_run_dir(tmp_path / "run", False), "cpu", config, progress=False).fit()
    splits = ["same_pose_same_view", "novel_pose_novel_view", "cross_dataset"]
    report = evaluate_autoencoder_run(
        tmp_path / "run", EvalRequest(tuple(splits), 1, progress=False, grids=1, refine_steps=2)
    )
    assert report["splits"]["same_pose_same_view"]["n_views"] == 1
    assert set(report["splits"]["novel_pose_novel_view"]["mean_code"]) == {"mask_l2", "psnr", "ssim"}
    cross = report["splits"]["cross_dataset"]
    assert cross["reconstruction"]["n_views"] == 1 and cross["novel_pose"]["n_views"] == 2
    assert cross["novel_pose"]["refine_steps"] == 2 and set(cross["novel_pose"]["refined"]) == {
        "mask_l2",
        "psnr",
        "ssim",
    }
    md = (tmp_path / "run" / "eval" / "metrics.md").read_text()
    assert "| mean code (baseline) |" in md and "SURREAL novel pose" in md
    assert "| encoder + 2 refinement steps on the input | - | - |" in md
    assert len(list((tmp_path / "run" / "eval" / "grids").rglob("*.png"))) == 3


def test_cnn_autoencoder_fits_resumes_and_evaluates(sets, tmp_path, monkeypatch):
    monkeypatch.setenv("NARF_DATA", str(sets))
    config = _config(sets, "model.name=cnn", "model.image_size=32", "train.steps=2", "train.images_per_step=2")
    trainer = start_run(prepare_run_dir(tmp_path / "run", False), "cpu", config, progress=False)
    assert isinstance(trainer, CnnAutoencoderTrainer)
    trainer.fit()
    resumed = resume_run(tmp_path / "run", "cpu", progress=False)
    assert isinstance(resumed, CnnAutoencoderTrainer) and resumed.step == 2
    splits = ["same_pose_same_view", "cross_dataset"]
    report = evaluate_autoencoder_run(tmp_path / "run", EvalRequest(tuple(splits), 1, progress=False, grids=1))
    assert report["splits"]["same_pose_same_view"]["n_views"] == 1 and report["model"] == config.model.name
    assert "32^2 bone maps" in (tmp_path / "run" / "eval" / "metrics.md").read_text()
    with pytest.raises(ValueError, match="the CNN baseline renders no rays"):
        evaluate_autoencoder_run(tmp_path / "run", EvalRequest(("cross_dataset",), 1, progress=False, refine_steps=1))
    # the code reaches every conditional norm and is trained: its weights start at zero and each Adam step moves a
    # weight with a non-zero gradient by ~lr = 1e-3, so after 2 steps they sit far above 0
    model = load_checkpoint(tmp_path / "run")["model"]
    code_weights = [w[:, POSE_DIM:] for k, w in model.items() if k.endswith("affine.weight")]
    assert len(code_weights) == 30 and all(w.shape[1] == 16 and w.abs().max() > 1e-4 for w in code_weights)


def test_surreal_crop_camera_projects_the_body_into_the_crop(sets, body_model):
    import imageio.v2 as imageio

    info = sorted((sets / "synthetic" / "surreal").rglob("*_info.mat"))[0]
    clip = check_clip(info)
    with imageio.get_reader(str(info).replace("_info.mat", ".mp4")) as video:
        view, pose = surreal_view(clip, info, 2, body_model, video)
    assert view.image.shape == (128, 128, 3) and 0.05 < view.mask.mean() < 0.6
    assert np.linalg.det(view.camera.cam_from_world[:3, :3]) > 0  # right-handed after the flip
    joints = pose.world_from_joint[0, :, :3, 3].numpy().astype(np.float64)
    cam = joints @ view.camera.cam_from_world[:3, :3].T + view.camera.cam_from_world[:3, 3]
    uv = np.round((cam @ view.camera.K.T)[:, :2] / (cam @ view.camera.K.T)[:, 2:]).astype(int)
    torso = uv[[0, 3, 6, 9]]
    assert ((torso >= 0) & (torso < 128)).all() and all(view.mask[v, u] > 0.5 for u, v in torso)


def test_mixed_up_runs_and_settings_fail_clearly(sets, tmp_path, capsys, data_root_64):
    with pytest.raises(ConfigError, match="model.latent_dim: an autoencoder run needs a latent size"):
        load_config("ae_tiny", ["model.latent_dim=0"])
    with pytest.raises(ConfigError, match="model.latent_dim: only autoencoder runs use it"):
        load_config("tiny", ["model.latent_dim=8"])
    with pytest.raises(ConfigError, match="train.colour_jitter: only the NeRF-type autoencoders"):
        load_config("ae_tiny", ["model.name=cnn", "train.colour_jitter=0.3"])
    subject = ["--config", "tiny", "--data-root", str(data_root_64), "--quiet", "--set", "train.steps=2"]
    assert run_cli("narf-fit", cli_fit.main, [*subject, "--out", str(tmp_path / "subject")]) == 0
    code = run_cli("narf-eval", cli_eval.main, ["--run", str(tmp_path / "subject"), "--split", "cross_dataset"])
    assert code == 2 and "a subject run; 'cross_dataset' is not one of its splits" in capsys.readouterr().err
    resume = ["--out", str(tmp_path / "subject"), "--resume", "--kind", "autoencoder"]
    assert run_cli("narf-fit", cli_fit.main, resume) == 2  # a run resumes as the kind it was fitted as
    assert "--resume continues the run as it was configured" in capsys.readouterr().err
    config = _config(sets, "train.steps=1")
    start_run(prepare_run_dir(tmp_path / "ae", False), "cpu", config, progress=False).fit()
    code = run_cli("narf-eval", cli_eval.main, ["--run", str(tmp_path / "ae"), "--split", "novel_pose"])
    assert code == 2 and "an autoencoder run; 'novel_pose' is not one of its splits" in capsys.readouterr().err
    argv = ["--run", str(tmp_path / "ae"), "--split", "novel_pose_same_view", "--refine-steps", "5"]
    assert run_cli("narf-eval", cli_eval.main, argv) == 2
    assert "it needs --split cross_dataset or all" in capsys.readouterr().err
    argv = ["--run", str(tmp_path / "ae"), "--split", "novel_pose_same_view", "--samples", "4", "4"]
    assert run_cli("narf-eval", cli_eval.main, argv) == 2
    assert "an autoencoder run; --samples is for subject runs\n" in capsys.readouterr().err
    argv = ["--run", str(tmp_path / "ae"), "--split", "novel_pose_same_view", "--frame-step", "2"]
    assert run_cli("narf-eval", cli_eval.main, argv) == 2
    assert "an autoencoder run; --frame-step is for subject runs\n" in capsys.readouterr().err
    argv = ["--run", str(tmp_path / "subject"), "--refine-steps", "5"]
    assert run_cli("narf-eval", cli_eval.main, argv) == 2
    assert "--refine-steps is for autoencoder runs" in capsys.readouterr().err


def test_videos_of_encoded_people(sets, tmp_path, capsys):
    import imageio.v2 as imageio

    from pipelines.cli import render_video as cli_video

    config = _config(sets, "train.steps=2")
    start_run(prepare_run_dir(tmp_path / "ae", False), "cpu", config, progress=False).fit()
    render = str(sets / "thuman" / "same_view" / "render_128" / "color" / "color_00000009.png")
    info = str(sorted((sets / "synthetic" / "surreal").rglob("*_info.mat"))[0])
    base = ["--run", str(tmp_path / "ae"), "--frames", "3", "--quiet"]
    assert cli_video.main([*base, "--kind", "orbit", "--input", render, "--refine-steps", "2"]) == 0
    assert cli_video.main([*base, "--kind", "interpolate", "--input", f"{info}:1", "--input", render]) == 0
    frames = imageio.mimread(tmp_path / "ae" / "videos" / "interpolate.mp4")
    assert len(frames) == 3 and frames[0].shape[0] == 128 and frames[0].shape[1] >= 128 * 3
    code = run_cli("narf-render-video", cli_video.main, [*base, "--kind", "interpolate", "--input", render])
    assert code == 2 and "--kind interpolate takes 2 --input, got 1" in capsys.readouterr().err
    (tmp_path / "photo.png").write_bytes((sets / "thuman" / "synthetic.json").read_bytes())
    code = run_cli("narf-render-video", cli_video.main, [*base, "--input", str(tmp_path / "photo.png")])
    assert code == 2 and "an image without a skeleton" in capsys.readouterr().err
    code = run_cli("narf-render-video", cli_video.main, [*base, "--input", render, "--samples", "4", "2"])
    assert code == 2 and "--samples is for subject runs" in capsys.readouterr().err


def test_code_refinement_recovers_a_code_and_leaves_the_field_alone(sets, body_model):
    import imageio.v2 as imageio

    from fitting.evaluate import render_view
    from fitting.model_setup import make_field

    config = _config(sets)
    torch.manual_seed(0)  # the field's initial weights
    field = make_field(config).eval()
    info = sorted((sets / "synthetic" / "surreal").rglob("*_info.mat"))[0]
    clip = check_clip(info)
    with imageio.get_reader(str(info).replace("_info.mat", ".mp4")) as video:
        view, pose = surreal_view(clip, info, 0, body_model, video)
    # the crop camera at 32^2 (pixel centres: u' = (u + 0.5) / 4 - 0.5), which keeps the test to a few seconds
    K = np.diag([0.25, 0.25, 1.0]) @ view.camera.K + np.array([[0, 0, -0.375], [0, 0, -0.375], [0, 0, 0]])
    camera = dataclasses.replace(view.camera, K=K, width=32, height=32)
    gen = torch.Generator().manual_seed(1)
    truth = torch.randn(1, 2 * config.model.latent_dim, generator=gen)
    start = truth + 0.3 * torch.randn(truth.shape, generator=gen)
    target = render_view(field, camera, pose, config, truth)
    before = {k: v.clone() for k, v in field.state_dict().items()}

    def error(code):
        return float((render_view(field, camera, pose, config, code)["rgb"] - target["rgb"]).pow(2).mean())

    t = torch.as_tensor
    args = (t(K), t(camera.cam_from_world), pose, target["rgb"], target["mask"])
    assert refine_code(config, field, start, *args, steps=0) is start
    refined = refine_code(config, field, start, *args, steps=60, rays_per_step=256)
    # the target is this field's own render of ``truth``: 60 Adam steps of 0.01 must remove most of the error of a
    # 0.3-sigma perturbation (a no-op or a wrong-signed gradient would leave it or grow it). Not all of it: each step
    # sees 256 random pixels at Adam's fixed step size, and 32^2 pixels do not pin down every code entry (measured:
    # 0.29 of the error left)
    assert error(refined) < 0.5 * error(start)
    assert all(torch.equal(v, field.state_dict()[k]) for k, v in before.items())
    assert all(p.requires_grad for p in field.parameters()) and refined.requires_grad is False


def test_viewer_offers_the_people_and_blends_their_codes(sets, tmp_path):
    import browser

    from fitting.evaluate import render_view
    from pipelines.viewer.app import Viewer, autoencoder_viewer_data

    config = _config(sets, "train.steps=2")
    start_run(prepare_run_dir(tmp_path / "ae", False), "cpu", config, progress=False).fit()
    data = autoencoder_viewer_data(tmp_path / "ae", "cpu", preview=48, full=64)
    # 4 people x (2 training + 1 held-out poses) = 12 meshes, all offered (at most 16)
    assert len(data.people) == 12 and sum("held out" in p.name for p in data.people) == 4
    assert data.sources[0].count == 12 and len(data.cameras) == 12
    codes = torch.cat([p.code for p in data.people])
    assert codes.shape[0] == 12 and not torch.equal(codes[0], codes[1])
    # a person's skeleton is recovered from its own joint frames: posing it in its own pose gives those frames back
    pose = data.sources[0].make(3)
    pose.rest = data.people[3].rest
    np.testing.assert_allclose(pose.world_from_joint(), data.sources[0].make(3).world_from_joint(), atol=1e-9)
    render = render_view(data.field, data.cameras[0], pose.pose_batch(), data.config, 0.5 * (codes[:1] + codes[1:2]))
    assert render["rgb"].shape == (128, 128, 3)
    if browser.CHROMIUM is None or browser.CHROMEDRIVER is None:
        return  # the page itself is checked in tests/test_viewer.py where chromium is installed
    viewer = Viewer(data, "127.0.0.1", browser.free_port())
    driver = browser.chromium()
    try:
        driver.get(f"http://127.0.0.1:{viewer.server.get_port()}")
        session = browser.wait(lambda: next(iter(viewer.sessions.values()), None), 60, "the tab's session")
        browser.wait(lambda: session.full_shown == session.version or None, 60, "the first still frame")
        first = session.last_image.copy()
        session.person, session.other, session.blend = 0, 5, 1.0  # what the Person controls set
        session.touch()
        browser.wait(lambda: session.full_shown == session.version or None, 60, "the blended frame")
        assert torch.equal(session.latent(), data.people[5].code) and not np.array_equal(session.last_image, first)
    finally:
        driver.quit()
        viewer.stop()
