"""Motion capture on a fitted subject: AMASS / ZJU / SURREAL readers, slerp resampling, placement on the stage."""

import json

import imageio.v2 as imageio
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from pipelines.body.motion import Motion, Stage, load_motion, place, resample
from pipelines.cli import render_video as cli_video
from pipelines.cli.common import run_cli
from pipelines.datasets.amass import read_amass, write_amass
from pipelines.datasets.errors import CaptureError


def _walk(n=12):
    """A z-up AMASS-like walk: standing (root +90 deg about x turns SMPL's +y up onto +z), knees swinging,
    the pelvis moving 1 m along +x at 0.9 m height."""
    poses = np.zeros((n, 156))
    poses[:, 0] = np.pi / 2
    poses[:, 3 * 4] = 0.6 * np.sin(np.linspace(0, 2 * np.pi, n))  # left knee about x
    poses[:, 3 * 30] = 0.4  # a finger joint of SMPL+H: must not reach SMPL
    trans = np.stack([np.linspace(0, 1, n), np.zeros(n), np.full(n, 0.9)], axis=1)
    return poses, trans


def test_amass_reader(tmp_path):
    poses, trans = _walk()
    write_amass(tmp_path / "walk.npz", poses, trans, np.arange(16) * 0.1, "female", 120.0)
    motion = read_amass(tmp_path / "walk.npz")
    assert motion.poses.shape == (12, 72) and motion.fps == 120.0 and motion.gender == "female"
    np.testing.assert_array_equal(motion.poses[:, :66], poses[:, :66])
    assert not motion.poses[:, 66:].any()  # SMPL's hand joints stay at rest
    np.testing.assert_array_equal(motion.trans, trans)


def test_amass_reader_refuses_bad_files(tmp_path):
    poses, trans = _walk()
    np.savez(
        tmp_path / "pickled.npz",
        poses=poses,
        trans=trans,
        mocap_framerate=np.array(60.0),
        gender=np.array([{"x": 1}], dtype=object),
    )
    with pytest.raises(CaptureError, match="pickle"):
        read_amass(tmp_path / "pickled.npz")
    np.savez(tmp_path / "short.npz", poses=poses[:, :100], trans=trans, mocap_framerate=np.array(60.0))
    with pytest.raises(CaptureError, match=r"expected \(T, 156\)"):
        read_amass(tmp_path / "short.npz")
    np.savez(tmp_path / "norate.npz", poses=poses, trans=trans)
    with pytest.raises(CaptureError, match="missing keys"):
        read_amass(tmp_path / "norate.npz")
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(CaptureError, match="not an .npz archive .*starts with b'hello'") as caught:
        read_amass(tmp_path / "text.npz")
    assert "pickle" not in str(caught.value)  # numpy's message would call it pickled and advise allow_pickle
    (tmp_path / "clip.txt").write_text("x")
    with pytest.raises(CaptureError, match="not a motion"):
        load_motion(tmp_path / "clip.txt", np.zeros(3))


def test_resample_is_slerp_not_frame_dropping():
    # joint 4 turns 0 -> 90 -> 180 deg about z at 10 fps; the pelvis moves 1 m per frame
    angles = np.radians([0.0, 90.0, 180.0])
    rotations = np.zeros((3, 24, 3))
    rotations[:, 4, 2] = angles
    motion = Motion("test", rotations, np.stack([np.arange(3.0), np.zeros(3), np.zeros(3)], 1), 10.0, None)
    out = resample(motion, 20.0)
    assert out.n_frames == 5 and out.fps == 20.0
    # slerp of rotations about one axis interpolates the angle: 0, 45, 90, 135, 180 degrees
    got = np.degrees(Rotation.from_rotvec(out.rotations[:, 4]).magnitude())
    np.testing.assert_allclose(got, [0, 45, 90, 135, 180], atol=1e-9)
    np.testing.assert_allclose(out.pelvis[:, 0], [0, 0.5, 1, 1.5, 2], atol=1e-12)
    window = resample(motion, 20.0, start=1, n_frames=2)
    np.testing.assert_allclose(np.degrees(Rotation.from_rotvec(window.rotations[:, 4]).magnitude()), [90, 135])
    with pytest.raises(ValueError, match="--start 3"):
        resample(motion, 20.0, start=3)


def test_placement_stands_the_body_on_the_floor_facing_forward(body_model64):
    poses, trans = _walk()
    motion = Motion("walk", poses[:, :72].reshape(-1, 24, 3), trans, 30.0, np.array([0.0, 0.0, 1.0]))
    # a z-down stage like the synthetic captures', facing +y, floor at z = 0 (height -0 along up = -z)
    stage = Stage(np.array([0.0, 0.0, -1.0]), 0.0, np.array([0.2, -0.1, -0.9]), np.array([0.0, 1.0, 0.0]))
    shapes = np.zeros(10)
    params = place(motion, stage, body_model64, shapes)
    stack = [
        torch.as_tensor(np.stack([getattr(p, k) for p in params]), dtype=torch.float64)
        for k in ("poses", "rh", "th", "shapes")
    ]
    bodies = body_model64.pose_zju(*stack)
    heights = bodies.vertices.numpy() @ stage.up
    # float32 parameters (the ZJU files' dtype): ~1e-6 m after posing
    assert abs(heights.min() - stage.floor) < 1e-5  # the lowest point of the clip is on the floor
    rh = Rotation.from_rotvec(np.stack([p.rh for p in params]).astype(np.float64))
    np.testing.assert_allclose(rh.apply([0.0, 1.0, 0.0]), np.tile(stage.up, (12, 1)), atol=1e-6)  # standing
    np.testing.assert_allclose(rh[0].apply([0.0, 0.0, 1.0]), stage.forward, atol=1e-6)  # facing forward
    pelvis = bodies.world_from_joint[:, 0, :3, 3].numpy()
    np.testing.assert_allclose(pelvis[0, :2], stage.centre[:2], atol=1e-5)  # starts at the stage centre
    # the walk keeps its length and its side relative to the body: it faces -y with +z up and walks along
    # +x = -(facing x up); on the stage it faces +y with -z up, and -(y x -z) = +x
    np.testing.assert_allclose(pelvis[-1] - pelvis[0], [1.0, 0.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(np.stack([p.poses for p in params])[:, 3:], poses[:, 3:72], atol=1e-6)


def test_render_video_plays_every_motion_kind(tiny_run, data_root_64, tmp_path, capsys):
    poses, trans = _walk(6)
    poses[3:, 3 * 16 + 2] = 2.5  # left shoulder far outside the training motion in frames 3-5
    write_amass(tmp_path / "walk.npz", poses, trans, np.zeros(16), "male", 20.0)
    args = ["--run", str(tiny_run), "--kind", "poses", "--quiet", "--fps", "10"]
    out = tmp_path / "amass.mp4"
    assert (
        run_cli("narf-render-video", cli_video.main, [*args, "--motion", str(tmp_path / "walk.npz"), "--out", str(out)])
        == 0
    )
    assert len([f for f in imageio.get_reader(out)]) == 3  # 6 frames at 20 fps = 0.25 s -> 3 frames at 10 fps
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["frames"] == 3 and [e["frame"] for e in report["out_of_range"]][-1] == 2
    assert "left_shoulder" in report["out_of_range"][-1]["parts"]
    assert "leave the trained pose range" in capsys.readouterr().err
    zju = data_root_64 / "synthetic" / "taichi" / "new_params"
    out = tmp_path / "zju.mp4"
    assert (
        run_cli(
            "narf-render-video",
            cli_video.main,
            [*args, "--motion", str(zju), "--motion-fps", "10", "--frames", "4", "--out", str(out)],
        )
        == 0
    )
    assert len([f for f in imageio.get_reader(out)]) == 4
    assert run_cli("narf-render-video", cli_video.main, [*args, "--motion", str(tmp_path / "nope.npz")]) == 2
    assert "no such motion" in capsys.readouterr().err
    assert (
        run_cli("narf-render-video", cli_video.main, [*args, "--motion", str(tmp_path / "walk.npz"), "--start", "9"])
        == 2
    )
    assert "--start 9" in capsys.readouterr().err
    from pipelines.cli import export_mesh

    mesh = ["--run", str(tiny_run), "--motion", str(tmp_path / "walk.npz"), "--out", str(tmp_path / "m.ply")]
    assert run_cli("narf-export-mesh", export_mesh.main, [*mesh, "--frames", "100:200", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--frames 100: " in err and "walk.npz has 6 frames (0..5)" in err and "--start" not in err


def test_surreal_clip_as_motion(tmp_path):
    from pipelines.synthetic.surreal_files import write_surreal_clip

    n = 3
    pose = np.zeros((n, 72))
    joints3d = np.zeros((n, 24, 3))
    joints3d[:, 0] = [[0.0, -1.0, 1.0], [0.1, -1.0, 1.0], [0.2, -1.0, 1.0]]
    segm = np.zeros((n, 240, 320), np.uint8)
    depth = np.full((n, 240, 320), 1e10, np.float32)
    frames = np.zeros((n, 240, 320, 3), np.uint8)
    info = write_surreal_clip(
        tmp_path, "01_01_c0001", frames, segm, depth, pose, np.zeros(10), 0.5, np.array([7.6, -1, 1.1]), joints3d, 1
    )
    motion = load_motion(info, np.zeros(3))
    assert motion.fps == 30.0 and motion.n_frames == 3
    np.testing.assert_array_equal(motion.pelvis, joints3d[:, 0])
    from pipelines.body.surreal import surreal_world_pose

    expected = np.stack([surreal_world_pose(p, 0.5)[:3] for p in pose])
    np.testing.assert_array_equal(motion.rotations[:, 0], expected)
    assert motion.up is None  # SURREAL's up is taken from the bodies' orientation (estimated_up)
