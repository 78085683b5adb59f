"""Videos from a fitted run (``narf-render-video``): camera orbit, pose sequences, bone-length edits."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from fitting.evaluate import render_view
from fitting.plots import to_numpy
from fitting.video import video_frame, write_mp4
from narf.kinematics import SMPL_PARENTS, rigid_from_rotvec_translation
from pipelines.body.model import BodyModel, pose_batch, posed_from_rest_joints
from pipelines.datasets.zju_mocap import CaptureError, read_params
from pipelines.fit_session import load_run
from pipelines.synthetic.scene import look_at

KINDS = ("orbit", "poses", "bones")
#: Bone-length edit: joints whose offset from their parent is scaled (legs: knees, ankles, feet).
LEG_JOINTS = (4, 5, 7, 8, 10, 11)


def up_vector(cameras) -> np.ndarray:
    """World 'up' estimated as the normalised mean of the cameras' -R[1, :] rows (never hard-coded)."""
    up = -np.mean([c.cam_from_world[1, :3] for c in cameras], axis=0)
    return up / np.linalg.norm(up)


def orbit_cameras(cameras, centre: np.ndarray, n_frames: int) -> list:
    """A full circle of cameras around ``centre`` at the rig's mean distance and height."""
    up = up_vector(cameras)
    centres = np.array([c.centre for c in cameras])
    offsets = centres - centre
    height = float(np.mean(offsets @ up))
    radius = float(np.mean(np.linalg.norm(offsets - np.outer(offsets @ up, up), axis=1)))
    start = offsets[0] - (offsets[0] @ up) * up
    start /= np.linalg.norm(start)
    side = np.cross(up, start)
    out = []
    for k in range(n_frames):
        angle = 2 * np.pi * k / n_frames
        position = centre + radius * (np.cos(angle) * start + np.sin(angle) * side) + height * up
        out.append(replace(cameras[0], cam_from_world=look_at(position, centre, down=-up)))
    return out


def scaled_skeleton(rest: torch.Tensor, joints: tuple[int, ...], scale: float) -> torch.Tensor:
    """Rest joints with the offsets of ``joints`` from their parents scaled (children follow)."""
    out = rest.clone()
    for j in range(1, 24):
        parent = SMPL_PARENTS[j]
        offset = rest[:, j] - rest[:, parent]
        out[:, j] = out[:, parent] + (scale if j in joints else 1.0) * offset
    return out


def _params_sequence(capture, params_dir: Path | None, frames: list[int]):
    if params_dir is None:
        return [capture.params(f) for f in frames]
    files = sorted(Path(params_dir).glob("*.npy"), key=lambda p: int(p.stem) if p.stem.isdigit() else 0)
    if not files:
        raise CaptureError(f"{params_dir}: no SMPL params files (*.npy)")
    return [read_params(p) for p in files]


def render_video(
    run_dir: Path,
    kind: str,
    out: Path,
    n_frames: int = 60,
    fps: int = 24,
    device: str = "cpu",
    params_dir: Path | None = None,
    camera_index: int | None = None,
    scale: float = 1.3,
    progress: bool = True,
) -> Path:
    """Render ``kind`` (orbit | poses | bones) of a fitted run to an H.264 mp4 of RGB | depth | segmentation."""
    if kind not in KINDS:
        raise ValueError(f"unknown video kind '{kind}'; choose from {', '.join(KINDS)}")
    run = load_run(run_dir, device)
    config, field, capture, protocol, body_model = run.config, run.field, run.capture, run.protocol, run.body_model
    held = (protocol.novel_frames or protocol.train_frames)[0]
    view = camera_index if camera_index is not None else (protocol.test_views or protocol.train_views)[0]
    if not 0 <= view < capture.n_cameras:
        raise ValueError(f"camera {view} out of range ({capture.n_cameras} cameras)")
    camera = capture.load_frame(held, view).camera
    base = capture.params(held)
    shapes = torch.as_tensor(base.shapes)[None]
    frames_out = []
    if kind == "poses":
        sequence = list(protocol.novel_frames or protocol.train_frames)[:n_frames]
        params = _params_sequence(capture, params_dir, sequence)[:n_frames]
    else:
        params = [base] * n_frames
    cameras = (
        orbit_cameras([c.scaled(capture.ratio) for c in capture.cameras], _pelvis(body_model, base), n_frames)
        if kind == "orbit"
        else [camera] * len(params)
    )
    for k, (p, cam) in enumerate(
        tqdm(list(zip(params, cameras)), desc=f"video {kind}", unit="frame", disable=not progress)
    ):
        args = [torch.as_tensor(v)[None] for v in (p.poses, p.rh, p.th)]
        with torch.no_grad():
            if kind == "bones":
                factor = 1 + (scale - 1) * 0.5 * (1 - np.cos(2 * np.pi * k / max(len(params) - 1, 1)))
                rest = scaled_skeleton(body_model.rest_joints(shapes), LEG_JOINTS, float(factor))
                pose = pose_batch(posed_from_rest_joints(args[0], rigid_from_rotvec_translation(*args[1:]), rest))
            else:
                pose = pose_batch(body_model.pose_zju(*args, shapes))
        frames_out.append(video_frame(to_numpy(render_view(field, cam, pose.to(device), config))))
    return write_mp4(out, frames_out, fps)


def _pelvis(body_model: BodyModel, params) -> np.ndarray:
    with torch.no_grad():
        body = body_model.pose_zju(
            *(torch.as_tensor(v)[None] for v in (params.poses, params.rh, params.th, params.shapes))
        )
    return body.world_from_joint[0, 0, :3, 3].numpy().astype(np.float64)
