"""The rigid-object set (supplement Table B): written by narf-synth, read back, fitted and evaluated by the CLIs."""

import json
import shutil

import numpy as np
import pytest
import torch

from narf.geometry import se3_exp
from pipelines.cli import eval as cli_eval
from pipelines.cli import fit, render_video, synth
from pipelines.cli.common import run_cli
from pipelines.datasets.rigid import load_rigid_views, open_rigid, rigid_pose_batch
from pipelines.synthetic.rigid import RigidSynthConfig, generate_rigid, vehicle

SIZE = 48


@pytest.fixture(scope="module")
def rigid_set(tmp_path_factory):
    return generate_rigid(tmp_path_factory.mktemp("rigid") / "set", RigidSynthConfig(6, 2, SIZE), progress=False)


def test_set_reads_back_with_cameras_aimed_at_the_object(rigid_set):
    rigid = open_rigid(rigid_set)
    assert (rigid.size, rigid.counts, rigid.radius) == (SIZE, {"train": 6, "test": 2}, 1.1)
    views, poses = load_rigid_views(rigid, "train")
    for view, world_from_object in zip(views, poses.world_from_part[:, 0].double().numpy()):
        # the camera looks at the object's origin: it projects to the principal point (c = (SIZE - 1) / 2);
        # float32 poses on disk -> 1e-4 px
        centre = view.camera.K @ (view.camera.cam_from_world @ world_from_object)[:3, 3]
        np.testing.assert_allclose(centre[:2] / centre[2], [(SIZE - 1) / 2] * 2, atol=1e-4)
        assert 0.05 < view.mask.mean() < 0.9 and view.image[view.mask == 0].max() == 0
    # the object is inside its box (half-extent 1 in radius units) in every pose
    assert np.linalg.norm(vehicle().mesh.vertices, axis=1).max() < rigid.radius


def test_pose_features_are_the_log_of_the_normalised_pose():
    rotation = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    world_from_object = torch.eye(4, dtype=torch.float64)[None].clone()
    world_from_object[0, :3, :3], world_from_object[0, :3, 3] = rotation, torch.tensor([0.2, -0.4, 0.1])
    pose = rigid_pose_batch(world_from_object, 2.0)
    # hand-computed: a quarter turn about z -> omega = (0, 0, pi/2); exp(xi) gives back [R | t / s]
    np.testing.assert_allclose(pose.pose_features[0, 0, :3], [0, 0, np.pi / 2], atol=1e-12)
    expected = world_from_object[0].clone()
    expected[:3, 3] /= 2.0
    np.testing.assert_allclose(se3_exp(pose.pose_features[0, 0]).detach(), expected, atol=1e-12)  # float64 round trip
    assert pose.bone_lengths.shape == (1, 0) and pose.reach.tolist() == [2.0]


def test_fit_eval_and_bad_input(rigid_set, tmp_path, capsys):
    run = tmp_path / "run"
    argv = ["--kind", "rigid", "--data-root", str(rigid_set), "--config", "rigid_tiny", "--out", str(run)]
    assert run_cli("narf-fit", fit.main, [*argv, "--model", "rp_nerf", "--quiet"]) == 0
    assert run_cli("narf-eval", cli_eval.main, ["--run", str(run), "--quiet"]) == 0
    report = json.loads((run / "eval" / "metrics.json").read_text())
    assert report["model"] == "rp_nerf" and report["splits"]["test"]["n_views"] == 2
    assert set(report["splits"]["test"]["full"]) == {"mask_l2", "psnr", "ssim"}
    capsys.readouterr()
    assert run_cli("narf-render-video", render_video.main, ["--run", str(run), "--frames", "2"]) == 2
    assert "a rigid run; it renders no videos" in capsys.readouterr().err
    assert run_cli("narf-eval", cli_eval.main, ["--run", str(run), "--samples", "4", "4", "--quiet"]) == 2
    assert "a rigid run; --samples is for subject runs" in capsys.readouterr().err
    assert run_cli("narf-eval", cli_eval.main, ["--run", str(run), "--frame-step", "2", "--quiet"]) == 2
    assert "a rigid run; --frame-step is for subject runs" in capsys.readouterr().err
    assert run_cli("narf-fit", fit.main, [*argv[:-1], str(tmp_path / "x"), "--model", "narf_d"]) == 2
    assert "'narf_d' is not a rigid-object model" in capsys.readouterr().err
    broken = tmp_path / "broken"
    shutil.copytree(rigid_set, broken)
    (broken / "test" / f"render_{SIZE}" / "K.npy").unlink()
    argv[3], argv[-1] = str(broken), str(tmp_path / "y")
    assert run_cli("narf-fit", fit.main, [*argv, "--quiet"]) == 2
    assert f"render_{SIZE}/K.npy: missing" in capsys.readouterr().err  # one line naming the file
    assert not (tmp_path / "y" / "checkpoint.pt").exists()


def test_narf_synth_writes_and_reuses_the_set(tmp_path, capsys):
    argv = ["--dataset", "rigid", "--out", str(tmp_path / "r"), "--train-images", "2", "--test-images", "1"]
    assert run_cli("narf-synth", synth.main, [*argv, "--resolution", "16"]) == 0
    assert open_rigid(tmp_path / "r").counts == {"train": 2, "test": 1}
    capsys.readouterr()
    assert run_cli("narf-synth", synth.main, [*argv, "--resolution", "16"]) == 0
    assert "already holds this rigid set" in capsys.readouterr().out
    assert run_cli("narf-synth", synth.main, [*argv, "--resolution", "8"]) == 2  # below 16 px: refused
