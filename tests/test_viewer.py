"""narf-view: camera and pose maths against references, camera paths, the command's refusals, and the page in a
real browser (headless chromium with software WebGL, where installed)."""

import json
import os
from dataclasses import replace

import browser
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from narf.kinematics import SMPL_PARENTS
from pipelines.datasets.camera import Camera
from pipelines.datasets.camera_path import CameraPath, Keyframe, interpolate, intrinsics, read_camera_path
from pipelines.datasets.zju_mocap import SmplParams
from pipelines.viewer.avatar import BONE_GROUPS, AvatarPose, camera_from_viewer, viewer_from_camera, z_depth


def _camera(width=64, height=48) -> Camera:
    rotation = Rotation.from_euler("xyz", [100, -20, 30], degrees=True).as_matrix()
    cam_from_world = np.eye(4)
    cam_from_world[:3, :3], cam_from_world[:3, 3] = rotation, [0.1, -0.2, 3.0]
    return Camera("c", intrinsics(width, height, 40.0), np.zeros(5), cam_from_world, width, height)


def test_viewer_camera_round_trip():
    camera = _camera()
    position, wxyz, fov = viewer_from_camera(camera)
    back = camera_from_viewer(position, wxyz, fov, 64 / 48, 64)
    # float64 quaternion and matrix round trip: ~1e-15
    np.testing.assert_allclose(back.cam_from_world, camera.cam_from_world, atol=1e-12)
    np.testing.assert_allclose(back.K, camera.K, atol=1e-9)
    assert (back.width, back.height) == (64, 48) and np.degrees(fov) == pytest.approx(40.0)
    # a point on the optical axis projects to the image centre
    centre = position + 2.0 * back.cam_from_world[2, :3]
    x = back.K @ (back.cam_from_world[:3, :3] @ centre + back.cam_from_world[:3, 3])
    np.testing.assert_allclose(x[:2] / x[2], [31.5, 23.5], atol=1e-9)


def test_z_depth_is_along_the_optical_axis():
    K = intrinsics(5, 3, 60.0)
    ray_length = np.full((3, 5), 2.0)
    z = z_depth(ray_length, np.ones((3, 5)), K, far=9.0)
    u = np.arange(5) - 2.0
    # pixel (u, v) sees direction (u / f, v / f, 1) normalised: z = 2 / sqrt(1 + (u^2 + v^2) / f^2)
    expected = 2.0 / np.sqrt(1 + (u[None] ** 2 + (np.arange(3) - 1.0)[:, None] ** 2) / K[0, 0] ** 2)
    np.testing.assert_allclose(z, expected, rtol=1e-6)
    assert z_depth(ray_length, np.zeros((3, 5)), K, far=9.0).max() == 9.0


def _params(rng) -> SmplParams:
    return SmplParams(
        rng.normal(0, 0.3, 72).astype(np.float32),
        rng.normal(0, 0.5, 3).astype(np.float32),
        np.array([0.2, 0.1, 1.0], np.float32),
        rng.normal(0, 0.5, 10).astype(np.float32),
    )


def _avatar(params, body_model) -> AvatarPose:
    rest = body_model.rest_joints(torch.as_tensor(params.shapes)[None])[0].double().numpy()
    return AvatarPose.from_params(params, rest)


def test_avatar_pose_is_the_body_models_pose(body_model):
    from pipelines.body.model import pose_batch

    params = _params(np.random.default_rng(4))
    mine = _avatar(params, body_model).pose_batch()
    with torch.no_grad():
        reference = pose_batch(
            body_model.pose_zju(
                *(torch.as_tensor(v)[None] for v in (params.poses, params.rh, params.th, params.shapes))
            )
        )
    # float64 kinematics here against the float32 body model, and the skeleton recovered from the frames: ~1e-6
    for key in ("world_from_part", "reach", "bone_lengths", "pose_features", "rest_offsets", "world_from_joint"):
        np.testing.assert_allclose(getattr(mine, key).numpy(), getattr(reference, key).numpy(), atol=2e-5, err_msg=key)
    # a pose given as joint frames (THUman, SURREAL) comes back as the same frames
    frames = reference.world_from_joint[0].double().numpy()
    np.testing.assert_allclose(AvatarPose.from_joints(frames).world_from_joint(), frames, atol=1e-6)


def test_joint_handle_sets_the_joint_rotation_and_keeps_the_rest(body_model):
    pose = _avatar(_params(np.random.default_rng(1)), body_model)
    before = pose.world_from_joint()
    wanted = Rotation.from_euler("zyx", [40, -10, 70], degrees=True).as_matrix()
    for joint in (0, 18):
        pose.rotate_joint(joint, wanted)
        after = pose.world_from_joint()
        # float64 kinematics: ~1e-15 per product
        np.testing.assert_allclose(after[joint, :3, :3], wanted, atol=1e-10)
        untouched = [j for j in range(24) if j != joint and not _descends(j, joint)]
        np.testing.assert_allclose(after[untouched], before[untouched], atol=1e-10)
        np.testing.assert_allclose(after[joint, :3, 3], before[joint, :3, 3], atol=1e-10)  # turns about itself
        before = after


def _descends(j: int, ancestor: int) -> bool:
    while j >= 0:
        j = SMPL_PARENTS[j]
        if j == ancestor:
            return True
    return False


def test_bone_sliders_scale_their_bones_only(body_model):
    pose = _avatar(_params(np.random.default_rng(2)), body_model)
    joints = pose.world_from_joint()[:, :3, 3]
    pose.bone_scales["legs"] = 1.3
    scaled = pose.world_from_joint()[:, :3, 3]
    offsets = lambda p: np.linalg.norm(p[1:] - p[list(SMPL_PARENTS[1:])], axis=-1)  # noqa: E731
    ratio = offsets(scaled) / offsets(joints)
    legs = np.array([j in BONE_GROUPS["legs"] for j in range(1, 24)])
    np.testing.assert_allclose(ratio[legs], 1.3, rtol=1e-10)
    np.testing.assert_allclose(ratio[~legs], 1.0, rtol=1e-10)


def test_camera_path_round_trip_and_interpolation(tmp_path):
    a, b = _camera(), _camera()
    turned = np.eye(4)
    turned[:3, :3] = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    b = replace(b, cam_from_world=turned @ a.cam_from_world)
    path = CameraPath(64, 48, [Keyframe(a.cam_from_world, 40.0, 0), Keyframe(b.cam_from_world, 60.0, 10)])
    file = tmp_path / "path.json"
    file.write_text(json.dumps(path.to_json()))
    back = read_camera_path(file)
    views = interpolate(back, 5)
    np.testing.assert_allclose(views[0].cam_from_world, a.cam_from_world, atol=1e-12)
    np.testing.assert_allclose(views[-1].cam_from_world, b.cam_from_world, atol=1e-12)
    # halfway: the camera has turned 45 degrees about its own y axis, the same centre, fov and frame halfway
    middle = views[2].cam_from_world[:3, :3] @ a.cam_from_world[:3, :3].T
    assert Rotation.from_matrix(middle).magnitude() == pytest.approx(np.pi / 4)
    assert views[2].fov_y_degrees == pytest.approx(50.0) and views[2].frame == 5
    for bad, message in (
        ({"format": "x"}, "not a camera path"),
        ({**path.to_json(), "keyframes": []}, "no keyframes"),
        ({**path.to_json(), "width": 3}, "width and height"),
    ):
        file.write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=message):
            read_camera_path(file)
    mirror, lifted = a.cam_from_world.copy(), a.cam_from_world.copy()
    mirror[:3, 0] *= -1  # still orthonormal, determinant -1
    lifted[3] = [0, 0, 0.5, 1]
    first = path.to_json()["keyframes"][0]
    for keys, message in (
        ([{**first, "cam_from_world": mirror.tolist()}], "mirrors the world"),
        ([first, {**first, "cam_from_world": mirror.tolist()}], "keyframe 1: cam_from_world mirrors"),
        ([{**first, "cam_from_world": lifted.tolist()}], "bottom row must be 0 0 0 1"),
        ([{**first, "frame": True}], "frame an integer"),
    ):
        bad = {**path.to_json(), "keyframes": keys}
        file.write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=message):
            read_camera_path(file)


def test_render_video_flies_a_camera_path(tiny_run, tmp_path):
    from pipelines.cli import render_video
    from pipelines.cli.common import run_cli
    from pipelines.runs.subject.session import load_run

    camera = load_run(tiny_run).capture.cameras[0]
    path = CameraPath(32, 24, [Keyframe(camera.cam_from_world, 40.0, 0), Keyframe(camera.cam_from_world, 30.0, 3)])
    file = tmp_path / "path.json"
    file.write_text(json.dumps(path.to_json()))
    out = tmp_path / "path.mp4"
    args = ["--run", str(tiny_run), "--camera-path", str(file), "--frames", "3", "--out", str(out), "--quiet"]
    assert run_cli("narf-render-video", render_video.main, args) == 0 and out.stat().st_size > 0
    path.keyframes[1].frame = 10_000
    file.write_text(json.dumps(path.to_json()))
    assert run_cli("narf-render-video", render_video.main, args) == 2


@pytest.mark.skipif(browser.CHROMIUM is None or browser.CHROMEDRIVER is None, reason=browser.MISSING)
def test_the_page_shows_orbits_and_reposes_the_avatar(tiny_run, data_root_64):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    from pipelines.viewer.app import Viewer, viewer_data

    motion = data_root_64 / "synthetic" / "taichi" / "new_params"
    data = viewer_data(tiny_run, motion, "cpu", preview=96, full=160)
    viewer = Viewer(data, "127.0.0.1", browser.free_port())
    driver = browser.chromium()
    try:
        driver.get(f"http://127.0.0.1:{viewer.server.get_port()}")
        session = browser.wait(lambda: next(iter(viewer.sessions.values()), None), 60, "the tab's session")
        browser.wait(lambda: session.full_shown == session.version, 60, "the still frame")
        first = session.last_image.copy()
        # the page shows the render: the background image covers the canvas (the render's black background,
        # where viser's own is white), and the avatar's pixels are there
        page = browser.wait(
            lambda: (lambda p: p if (p.sum(-1) < 30).mean() > 0.5 else None)(browser.page_pixels(driver, "1-first")),
            30,
            "the rendered image on the page",
        )
        assert (first.sum(-1) > 30).mean() > 0.005 and (page.sum(-1) > 30).mean() > 0.001
        # dragging orbits: the tab's camera moves and a new image arrives
        position = np.array(session.client.camera.position)
        canvas = driver.find_element(By.TAG_NAME, "canvas")
        ActionChains(driver).move_to_element(canvas).click_and_hold().move_by_offset(120, 0).release().perform()
        browser.wait(
            lambda: np.linalg.norm(np.array(session.client.camera.position) - position) > 1e-3, 30, "the camera to move"
        )
        browser.wait(
            lambda: session.full_shown == session.version and not np.array_equal(session.last_image, first),
            60,
            "the orbited frame",
        )
        orbited = session.last_image.copy()
        browser.page_pixels(driver, "2-orbited")
        # the frame slider re-poses the avatar: focus it and step it with the arrow key
        slider = driver.find_elements(By.CSS_SELECTOR, "[role=slider]")[0]
        slider.click()
        for _ in range(3):
            slider.send_keys(Keys.ARROW_RIGHT)
        browser.wait(lambda: session.index > 0, 30, "the frame slider to move")
        browser.wait(
            lambda: session.full_shown == session.version and not np.array_equal(session.last_image, orbited),
            60,
            "the reposed frame",
        )
        browser.page_pixels(driver, "3-reposed")
        expected = data.sources[0].make(session.index).world_from_joint()
        np.testing.assert_array_equal(session.pose.world_from_joint(), expected)
        # the other controls, set as the page sets them (a GUI value assigned here fires the same callbacks)
        session.hand_box.value = True  # rotation handles at the 24 joints, placed at the joints
        assert len(session.handles) == 24
        np.testing.assert_allclose(session.handles[18].position, session.pose.world_from_joint()[18, :3, 3], atol=1e-6)
        before, shown = session.pose.world_from_joint(), session.full_shown
        turned = Rotation.from_euler("x", 60, degrees=True) * Rotation.from_matrix(before[18, :3, :3])
        x, y, z, w = turned.as_quat()
        session.handles[18].wxyz = (w, x, y, z)
        session._turn(18, session.handles[18])  # what dragging the left elbow's handle calls
        np.testing.assert_allclose(session.pose.world_from_joint()[18, :3, :3], turned.as_matrix(), atol=1e-9)
        session.bone_sliders["legs"].value = 1.3
        assert session.pose.bone_scales["legs"] == 1.3
        session.mode_menu.value = "depth"
        browser.wait(lambda: session.full_shown > shown and session.full_shown == session.version or None, 60, "depth")
        browser.page_pixels(driver, "4-posed-by-hand-depth")
        screenshot = session.screenshot()
        assert screenshot.parent == tiny_run / "viewer" / "screenshots" and screenshot.stat().st_size > 0
        session.add_keyframe()
        session.client.camera.position = np.array(session.client.camera.position) + 0.3
        session.add_keyframe()
        saved = read_camera_path(session.save_camera_path())
        assert len(saved.keyframes) == 2 and saved.keyframes[0].frame == session.index
        assert not np.allclose(saved.keyframes[0].cam_from_world, saved.keyframes[1].cam_from_world)
        session.hand_box.value = False
        assert not session.handles
        # the motion plays: switch the source, press play, and the frame moves on by itself
        session.source_menu.value = data.sources[1].name
        assert session.source is data.sources[1] and session.index == 0
        session.speed_slider.value = 4.0
        session._toggle_play()  # what the play / pause button calls
        browser.wait(lambda: session.index >= 2 or None, 30, "the motion to play")
        session._toggle_play()
        assert session.frame_slider.value == session.index
        # a second tab has a session of its own; closing it frees that session and leaves the first alone
        first_tab = driver.current_window_handle
        driver.switch_to.new_window("tab")
        driver.get(f"http://127.0.0.1:{viewer.server.get_port()}")
        browser.wait(lambda: len(viewer.sessions) == 2 or None, 60, "a second session")
        second = next(s for s in viewer.sessions.values() if s is not session)
        browser.wait(
            lambda: second.full_shown == second.version and second.full_shown > 0 or None, 60, "the second tab's frame"
        )
        assert second.index == 0 and session.index > 0
        driver.close()
        driver.switch_to.window(first_tab)
        browser.wait(lambda: len(viewer.sessions) == 1 or None, 30, "the closed tab's session to go")
        assert second.stop.is_set()
        browser.wait(lambda: not second.thread.is_alive() or None, 10, "the closed tab's thread to end")
    finally:
        driver.quit()
        viewer.stop()
    assert not viewer.sessions


def test_ctrl_c_stops_the_server(tiny_run):
    import signal
    import subprocess
    import sys

    import spawn

    argv = [sys.executable, "-c", "from pipelines.cli.view import entrypoint; entrypoint()"]
    argv += ["--run", str(tiny_run), "--port", str(browser.free_port())]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = spawn.popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    out, err = spawn.Reader(proc.stdout), spawn.Reader(proc.stderr)
    browser.wait(lambda: "serving" in out.text() or proc.poll() is not None or None, 120, "the server to start")
    proc.send_signal(signal.SIGINT)
    assert spawn.finish(proc, 30, "narf-view after Ctrl-C") == 130
    err.thread.join(timeout=5)
    assert "narf-view: interrupted" in err.text() and "Traceback" not in err.text()
