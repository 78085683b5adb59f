"""The body fit of a long take in windows (pipelines/prepare/body/fit.py, module docstring): the passes cover every
frame, the silhouette term is never built over more than a window's frames (what keeps memory flat in the take's
length), and the bodies of a take fitted in windows are as close to the truth as those fitted at once."""

import cv2
import numpy as np
import torch

from narf.kinematics import rigid_from_rotvec_translation, world_from_joints
from pipelines.body.model import BodyModel
from pipelines.cli import prepare_capture
from pipelines.cli.common import run_cli
from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.keypoints import TARGET_JOINTS
from pipelines.prepare.body import bodies as prepare_bodies
from pipelines.prepare.body.fit import FitSettings, _passes, continuous_rotvecs, fit_body, fit_steps
from pipelines.prepare.people.multiview import project


def test_the_passes_cover_every_frame_in_overlapping_windows():
    settings = FitSettings(window=100, window_overlap=10, silhouette_iterations=400)
    assert [(list(f), shared) for f, shared in _passes(settings, 100)] == [(list(range(100)), True)]
    assert len(_passes(FitSettings(window=0), 1000)[0][0]) == 1000
    passes = _passes(settings, 1000)
    spread, shared = passes[0]
    # the shared pass: 100 frames from the first to the last, evenly spread
    assert shared and len(spread) == 100 and spread[0] == 0 and spread[-1] == 999
    windows = [f for f, shared in passes[1:] if not shared]
    assert len(windows) == len(passes) - 1 and all(len(w) == 100 for w in windows)
    assert all(np.array_equal(w, np.arange(w[0], w[0] + 100)) for w in windows)
    starts = [int(w[0]) for w in windows]
    # each window starts 90 frames after the previous (10 fitted again), the last ends on the last frame
    assert starts[0] == 0 and all(b - a <= 90 for a, b in zip(starts, starts[1:])) and windows[-1][-1] == 999
    assert set(np.concatenate(windows)) == set(range(1000))
    assert fit_steps(settings, 1000) == 100 + 500 + 400 * len(passes)
    # a small window overlaps by at most half of itself, so that it always moves on
    assert [int(w[0]) for w, _ in _passes(FitSettings(window=4), 10)[1:]] == [0, 2, 4, 6]


def test_a_take_fitted_in_windows_matches_the_truth(recording, tmp_path, monkeypatch):
    built = []
    stage = prepare_bodies.silhouette_stage

    def recorded(*args, **kwargs):
        build = stage(*args, **kwargs)

        def counted(vertices, frames):
            built.append(len(frames))
            return build(vertices, frames)

        return counted

    monkeypatch.setattr(prepare_bodies, "silhouette_stage", recorded)
    rec, out = recording / "rec", tmp_path / "out"
    argv = [str(rec), "--out", str(out), "--keypoints", str(rec / "keypoints"), "--masks", str(rec / "masks")]
    # 100 silhouette iterations a pass (of 400 by default): five passes of four frames, the seams are what is tested
    extra = ["--quiet", "--fit-window", "4", "--silhouette-iterations", "100"]
    assert run_cli("narf-prepare-capture", prepare_capture.main, [*argv, *extra]) == 0
    # the spread frames, then windows at 0, 2, 4, 6 of the 10 frames: never more than 4 frames' masks at once
    assert built == [4, 4, 4, 4, 4]
    truth, fitted = ZjuCapture(recording / "truth"), ZjuCapture(out)
    true_vertices = np.stack([truth.vertices(f) for f in range(truth.n_frames)])
    vertices = np.stack([fitted.vertices(f) for f in range(fitted.n_frames)])
    # the bounds of the fit at once (tests/test_prepare_capture.py): joints leave limb twist and girth to the priors
    distance_cm = 100 * np.linalg.norm(true_vertices - vertices, axis=-1)
    assert np.median(distance_cm) < 3.0 and np.percentile(distance_cm, 95) < 10.0
    # no jump at the seams: each frame-to-frame step of the body's mean vertex within 1 cm of the truth's (1 px of
    # keypoint noise is about 1 cm at these cameras)
    steps = np.linalg.norm(np.diff(vertices.mean(1), axis=0), axis=-1)
    true_steps = np.linalg.norm(np.diff(true_vertices.mean(1), axis=0), axis=-1)
    assert np.abs(steps - true_steps).max() < 0.01, (steps, true_steps)


def _turning(angles: np.ndarray) -> np.ndarray:
    """Rotation vectors of turns by ``angles`` about a tilted axis, as OpenCV gives them (angle in [0, pi])."""
    axis = np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1])
    return np.stack([cv2.Rodrigues(cv2.Rodrigues(axis * a)[0])[0][:, 0] for a in angles])


def test_rotation_vectors_are_unwrapped_through_half_and_whole_turns():
    angles = np.linspace(2.5, 4 * np.pi + 1.0, 60)  # through pi, 2 pi, 3 pi, 4 pi
    wrapped = _turning(angles)
    assert np.linalg.norm(np.diff(wrapped, axis=0), axis=-1).max() > 5  # the jumps the fit would smooth across
    unwrapped = continuous_rotvecs(wrapped)
    step = angles[1] - angles[0]
    np.testing.assert_allclose(np.linalg.norm(np.diff(unwrapped, axis=0), axis=-1), step, rtol=1e-6)
    for a, b in zip(wrapped, unwrapped):  # the same rotations (float64 Rodrigues: 1e-9)
        np.testing.assert_allclose(cv2.Rodrigues(a)[0], cv2.Rodrigues(b)[0], atol=1e-9)


def _four_cameras_seeing(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(4, 3, 4) projections of cameras 3 m around (0, 0, 3), facing it, and the (F, 4, T, 3) exact keypoints
    (confidence 1) of the (F, T, 3) ``points`` in them."""
    K = np.array([[800.0, 0, 500], [0, 800.0, 500], [0, 0, 1]])
    P = []
    for angle in (0, np.pi / 2, np.pi, 3 * np.pi / 2):
        R = cv2.Rodrigues(np.array([0.0, angle, 0.0]))[0]
        P.append(K @ np.c_[R, -R @ np.array([3 * np.sin(angle), 0, 3 - 3 * np.cos(angle)])])
    P = np.array(P)
    ones = np.ones((*points.shape[:1], 4, points.shape[1], 1))
    return P, np.concatenate([np.moveaxis(project(P, points), 2, 1), ones], -1)


def test_a_body_turning_through_a_half_turn_is_fitted_in_every_frame():
    """Keypoints of the rest body turning about its vertical by 2.9 to 3.6 rad (through pi) in 10 frames, seen by
    4 cameras: every frame's targets and turn fitted. Without unwrapping, the smoothness on Rh
    pulled the frames around pi through the rotations between pi u and -pi u."""
    body = BodyModel()
    with torch.no_grad():
        rest = body.rest_joints(torch.zeros(1, 10))[0, list(TARGET_JOINTS)].numpy().astype(np.float64)
    turns = _turning(np.linspace(2.9, 3.6, 10))
    points = np.stack([rest @ cv2.Rodrigues(r)[0].T + [0, 0, 3.0] for r in turns])  # (F, T, 3)
    P, keypoints = _four_cameras_seeing(points)
    assert np.isfinite(keypoints).all()
    settings = FitSettings(global_iterations=100, iterations=200, silhouette_iterations=0)
    fitted = fit_body(body, P, np.full(4, 1000.0), keypoints, points, settings)
    # exact keypoints: every target within 0.5 cm (measured 0.08 cm; without unwrapping 32 cm near pi)
    assert np.linalg.norm(fitted.targets - points, axis=-1).mean(-1).max() < 0.005
    for r, rh in zip(turns, fitted.rh):
        gap = cv2.Rodrigues(cv2.Rodrigues(rh.astype(np.float64))[0] @ cv2.Rodrigues(r)[0].T)[0]
        # the torso's pose takes a few degrees of the turn where the smoothness acts from one side (the first and
        # last frames: 3.2 degrees measured); without unwrapping, 143 degrees
        assert np.degrees(np.linalg.norm(gap)) < 5.0


def test_limbs_far_from_rest_are_pulled_to_their_keypoints():
    """8 frames of a movement away from the rest pose (an arm raised overhead, the other lowered, a leg kicked back
    and its knee bent), exact keypoints in 4 cameras, fitted from the rest pose with the default settings (no
    masks). With Geman-McClure's reach from the start the last four frames' limbs lay too far from their targets to
    be pulled (24-95 cm off, measured); the graduated reach fits every frame (1.8 cm at most, measured)."""
    body = BodyModel()
    frames = 8
    poses = torch.zeros(frames, 24, 3)
    a = torch.linspace(0, 1, frames)
    poses[:, 17, 2], poses[:, 16, 2] = 2.6 * a + 0.2, 1.3 * a  # shoulders: right arm overhead, left arm down
    poses[:, 2, 0], poses[:, 5, 0] = -1.4 * a, 1.5 * a  # right hip back, right knee bent
    with torch.no_grad():
        rest = body.rest_joints(torch.zeros(1, 10)).expand(frames, -1, -1)
        at = rigid_from_rotvec_translation(torch.zeros(frames, 3), torch.tensor([[0, 0, 3.0]] * frames))
        points = world_from_joints(poses, rest, at)[:, list(TARGET_JOINTS), :3, 3].double().numpy()
    P, keypoints = _four_cameras_seeing(points)
    fitted = fit_body(body, P, np.full(4, 1000.0), keypoints, points, FitSettings(silhouette_iterations=0))
    # the smoothness pulls each frame towards neighbours up to 0.37 rad away, and the priors hold joints no target
    # observes: a few cm at the fastest frames, far below the tens of cm of a limb left near rest
    assert np.linalg.norm(fitted.targets - points, axis=-1).max() < 0.05
