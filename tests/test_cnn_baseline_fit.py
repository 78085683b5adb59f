"""The CNN baseline end to end: its inputs against hand-computed projections, a tiny fit, evaluation, video."""

import json

import numpy as np
import torch

from fitting.checkpoint import load_checkpoint
from fitting.config import load_config
from fitting.run_folder import prepare_run_dir
from narf.cnn_render import cnn_inputs, render_cnn_image, scaled_intrinsics
from narf.fields import CnnBaseline, model_spec
from pipelines.runs.fit import resume_run, start_run
from pipelines.runs.requests import EvalRequest, VideoRequest
from pipelines.runs.subject.evaluation import evaluate_run

CNN = ["model.name=cnn", "model.image_size=32", "train.images_per_step=4", "train.lr=0.001", "train.log_every=1"]


def _fit(root, out, *extra, resume=False):
    config = load_config("tiny", [f"data.data_root={root}", "data.ratio=1.0", *CNN, *extra])
    run = prepare_run_dir(out, resume)
    if resume:
        return resume_run(run, torch.device("cpu"), progress=False)
    return start_run(run, torch.device("cpu"), config, progress=False)


def test_scaled_intrinsics_keep_pixel_centres():
    """A point at pixel (u, v) of a 64 x 48 image lands at ((u + 0.5) s - 0.5) of the 32 x 32 resample."""
    K = torch.tensor([[50.0, 0, 31.5], [0, 52, 23.5], [0, 0, 1]])
    point = torch.tensor([0.1, -0.05, 1.0])
    uv = (K @ point)[:2] / point[2]
    small = scaled_intrinsics(K, 48, 64, 32)
    uv_small = (small @ point)[:2] / point[2]
    expected = torch.stack([(uv[0] + 0.5) * 32 / 64 - 0.5, (uv[1] + 0.5) * 32 / 48 - 0.5])
    # float32 on pixel values ~30: each of ~6 operations rounds by eps32 * 30 ~ 4e-6; a wrong pixel-centre
    # convention is off by 0.25 px
    assert torch.allclose(uv_small, expected, atol=1e-4)


def test_joint_squares_sit_where_the_joints_project():
    world_from_joint = torch.eye(4).repeat(1, 24, 1, 1)
    world_from_joint[0, :, :3, 3] = torch.stack(
        [torch.linspace(-0.3, 0.3, 24), torch.linspace(0.2, -0.2, 24), torch.full((24,), 2.0)], dim=1
    )
    K = torch.tensor([[[60.0, 0, 63.5], [0, 60, 63.5], [0, 0, 1]]])
    maps, bones = cnn_inputs(world_from_joint, torch.eye(4)[None], K, 128, 128, 64)
    assert maps.shape == (1, 46, 64, 64) and bones.shape == (1, 19 * 12)
    for joint in (0, 11, 23):
        x, y, z = world_from_joint[0, joint, :3, 3].tolist()
        u, v = ((60 * x / z + 63.5) + 0.5) / 2 - 0.5, ((60 * y / z + 63.5) + 0.5) / 2 - 0.5
        ys, xs = torch.nonzero(maps[0, 20 + joint] > 0, as_tuple=True)
        assert abs(xs.float().mean().item() - u) <= 0.5 and abs(ys.float().mean().item() - v) <= 0.5


def test_render_keeps_the_camera_size():
    model = CnnBaseline(image_size=32).eval()
    from narf.fields.common import PoseBatch

    joints = torch.eye(4).repeat(1, 24, 1, 1)
    joints[0, :, 2, 3] = 2.0
    pose = PoseBatch(
        joints[:, :19], torch.ones(1), torch.zeros(1, 19), torch.zeros(1, 19, 6), torch.zeros(1, 19, 3), joints
    )
    K = torch.tensor([[40.0, 0, 39.5], [0, 40, 29.5], [0, 0, 1]])
    with torch.no_grad():
        out = render_cnn_image(model, K, torch.eye(4), 60, 80, pose)
    assert out["rgb"].shape == (60, 80, 3) and out["mask"].shape == (60, 80) and not out["depth"].any()


def test_cnn_fit_loss_falls_resumes_and_evaluates(data_root_64, tmp_path):
    first = _fit(data_root_64, tmp_path / "run", "train.steps=40", "train.validate_every=40")
    for _ in range(20):
        first.train_step()
    first.checkpoint()
    del first  # "killed" after its checkpoint at step 20
    resumed = _fit(data_root_64, tmp_path / "run", resume=True)
    assert resumed.step == 20 and isinstance(resumed.field, CnnBaseline)
    result = resumed.fit()
    assert result.finished and result.step == 40 and load_checkpoint(tmp_path / "run")["step"] == 40
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert log[0]["step"] == 21 and log[-1]["step"] == 40
    # against the loss of the first step of a fresh model (same seed)
    assert np.mean([r["loss"] for r in log[-3:]]) < 0.5 * _initial_loss(data_root_64, tmp_path / "fresh")
    assert (tmp_path / "run" / "val" / "step_0000040.png").is_file()
    report = evaluate_run(tmp_path / "run", EvalRequest(("novel_pose_novel_view",), 2, progress=False))
    split = report["splits"]["novel_pose_novel_view"]
    assert model_spec(report["model"]).family == "image" and split["n_views"] == 2 and 5 < split["full"]["psnr"] < 60
    assert len(list((tmp_path / "run" / "eval" / "grids").rglob("*.png"))) == 2


def _initial_loss(root, out) -> float:
    trainer = _fit(root, out, "train.steps=1")
    return trainer.train_step()[0]


def test_cnn_video(data_root_64, tmp_path):
    import imageio.v2 as imageio

    from pipelines.runs.subject.video import render_video

    _fit(data_root_64, tmp_path / "run", "train.steps=2").fit()
    out = render_video(tmp_path / "run", VideoRequest("bones", tmp_path / "bones.mp4", frames=4, fps=4, progress=False))
    frames = imageio.mimread(out)
    assert len(frames) == 4 and frames[0].shape[1] == 2 * frames[0].shape[0]  # RGB | depth, no segmentation


def test_cnn_bad_input_is_named():
    import pytest

    from fitting.config import ConfigError
    from narf.fields.common import PoseBatch

    with pytest.raises(ConfigError, match="model.image_size"):
        load_config("tiny", ["model.name=cnn", "model.image_size=48"])
    pose = PoseBatch(
        torch.eye(4).repeat(1, 19, 1, 1),
        torch.ones(1),
        torch.zeros(1, 19),
        torch.zeros(1, 19, 6),
        torch.zeros(1, 19, 3),
    )
    with pytest.raises(ValueError, match="needs the pose's world_from_joint"):
        render_cnn_image(CnnBaseline(image_size=32), torch.eye(3), torch.eye(4), 32, 32, pose)
