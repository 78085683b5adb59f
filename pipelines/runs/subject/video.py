"""Videos from a fitted run (``narf-render-video``): camera orbit, pose sequences, bone-length edits."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from fitting.config import with_eval_samples
from fitting.evaluate import render_view
from fitting.files import atomic_write_bytes
from fitting.fitted import SavedRun, run_folder
from fitting.plots import to_numpy
from fitting.video import video_frame, write_mp4
from narf.kinematics import JOINT_NAMES, PART_JOINTS, SMPL_PARENTS, rigid_from_rotvec_translation
from pipelines.body.model import BodyModel, pose_batch, posed_from_rest_joints
from pipelines.body.motion import load_motion, place, resample, stage_of
from pipelines.datasets.camera_path import interpolate, intrinsics, read_camera_path
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.floor import camera_up
from pipelines.runs.requests import MotionClip, VideoRequest, refuse_options
from pipelines.runs.subject.session import LoadedRun, box_frames, load_run, poses_for_frames
from pipelines.synthetic.scene import look_at

VIDEO_KINDS = ("orbit", "poses", "bones", "path")
#: Bone-length edit: joints whose offset from their parent is scaled (legs: knees, ankles, feet).
LEG_JOINTS = (4, 5, 7, 8, 10, 11)


def orbit_cameras(cameras, centre: np.ndarray, n_frames: int) -> list:
    """A full circle of cameras around ``centre`` at the rig's mean distance and height."""
    up = camera_up(cameras)
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


#: A part more than this many degrees from its orientation in every training pose is out of the trained range.
OOD_DEGREES = 30.0


def part_rotation_gaps(train_world_from_part: torch.Tensor, world_from_part: torch.Tensor) -> np.ndarray:
    """Per frame and part, the angle (degrees) to the closest orientation of that part over the training poses.

    NARF's pose input xi keeps the global orientation (docs/model.md §1), so orientations are compared in the world.

    Args:
        train_world_from_part: (N, P, 4, 4). world_from_part: (T, P, 4, 4).

    Returns:
        (T, P) angles in degrees.
    """
    train, frames = train_world_from_part[..., :3, :3].double(), world_from_part[..., :3, :3].double()
    cosine = (torch.einsum("tpij,npij->tnp", frames, train) - 1) / 2  # trace(R_a^T R_b) = 2 cos + 1
    return np.degrees(np.arccos(cosine.clamp(-1, 1).amax(dim=1).numpy()))


def capture_stage(run: LoadedRun):
    """The capture's stage (``pipelines.body.motion.stage_of``) from up to 100 training frames, with their
    PoseBatch and betas (F, 10)."""
    frames = box_frames(list(run.protocol.train_frames), 100)
    train_pose, train_bodies, shapes = poses_for_frames(run, run.body_model, frames)
    pelvis = train_bodies.world_from_joint[:, 0].double().numpy()  # world rotation R(Rh) R(poses[:3]), position
    root_world = Rotation.from_matrix(pelvis[:, :3, :3]).as_rotvec()
    vertices = train_bodies.vertices.double().numpy()
    stage = stage_of(camera_up(run.capture.cameras), vertices, pelvis[:, :3, 3], root_world, run.capture.floor)
    return stage, train_pose, shapes


def motion_params(run: LoadedRun, clip: MotionClip, staged=None):
    """The subject's ZJU parameters performing ``clip`` of a motion file, placed on the capture's stage, and a report
    of the frames whose parts leave the trained range (``docs/design.md`` *Driving the avatar*). ``staged``: what
    :func:`capture_stage` returned, when the caller has it already."""
    body = run.body_model
    stage, train_pose, shapes = staged or capture_stage(run)
    rest_pelvis = body.rest_joints(shapes[:1].to(body.dtype))[0, 0].double().numpy()
    source = load_motion(clip.path, rest_pelvis, clip.source_fps)
    start = clip.start
    if not 0 <= start < source.n_frames:
        n = source.n_frames
        raise ValueError(f"{clip.flag} {start}: {clip.path} has {n} frames (0..{n - 1})")
    motion = resample(source, clip.fps or source.fps, start, clip.frames)
    params = place(motion, stage, body, shapes[0].double().numpy())
    stack = [torch.as_tensor(np.stack([getattr(p, k) for p in params])) for k in ("poses", "rh", "th", "shapes")]
    with torch.no_grad():
        gaps = part_rotation_gaps(train_pose.world_from_part, body.pose_zju(*stack).world_from_part)
    names = [JOINT_NAMES[j] for j in PART_JOINTS]
    outside = [
        {"frame": k, "parts": {names[i]: round(float(g), 1) for i, g in enumerate(row) if g > OOD_DEGREES}}
        for k, row in enumerate(gaps)
        if (row > OOD_DEGREES).any()
    ]
    report = {
        "motion": motion.source,
        "fps": motion.fps,
        "start": start,
        "frames": len(params),
        "threshold_degrees": OOD_DEGREES,
        "out_of_range": outside,
    }
    return params, report


def render_video(run: Path | SavedRun, request: VideoRequest) -> Path:
    """Render ``request.kind`` (orbit | poses | bones | path) of a fitted run to an H.264 mp4 of RGB | depth |
    segmentation (the kind table's entry point; options of autoencoder runs are refused).

    With ``motion`` (an AMASS .npz, a ZJU params folder or a SURREAL _info.mat) ``poses`` plays that motion at
    ``fps`` from source frame ``start`` (``motion_params``); its report goes to ``out`` with the suffix ``.json``,
    and the frames outside the trained range are named on stderr. ``path`` renders ``frames`` cameras along a
    ``camera_path`` saved by narf-view (``pipelines.datasets.camera_path``).
    """
    r = request
    run_dir = run_folder(run)
    refuse_options(run_dir, "subject", {"--input": r.inputs, "--refine-steps": r.refine_steps}, "autoencoder runs")
    if r.motion is not None and r.kind != "poses":
        raise ValueError("--motion plays with --kind poses")
    kind, n_frames, out, progress = r.kind, r.frames, r.out, r.progress
    if kind not in VIDEO_KINDS:
        raise ValueError(f"unknown video kind '{kind}'; choose from {', '.join(VIDEO_KINDS)}")
    run = load_run(run, r.device)
    if r.samples is not None:  # the renders' estimator of the volume integral (docs/model.md §7)
        run.config = with_eval_samples(run.config, *r.samples)
    config, field, capture, protocol, body_model = run.config, run.field, run.capture, run.protocol, run.body_model
    held = (protocol.novel_frames or protocol.train_frames)[0]
    view = r.camera if r.camera is not None else (protocol.test_views or protocol.train_views)[0]
    if not 0 <= view < capture.n_cameras:
        raise ValueError(f"camera {view} out of range ({capture.n_cameras} cameras)")
    camera = capture.load_frame(held, view).camera
    base = run.params(held)
    shapes = torch.as_tensor(base.shapes)[None]
    frames_out = []
    if kind == "path":
        params, cameras, shown = path_views(run, r.camera_path, n_frames)
    elif kind == "poses" and r.motion is not None:
        params, report = motion_params(run, MotionClip(Path(r.motion), r.start, n_frames, r.fps, r.motion_fps))
        _report_motion(report, Path(out).with_suffix(".json"))
        shown = [None] * len(params)  # a new motion: no capture frame
    elif kind == "poses":
        shown = list(protocol.novel_frames or protocol.train_frames)[:n_frames]
        params = [run.params(f) for f in shown]
    else:
        params, shown = [base] * n_frames, [held] * n_frames
    if kind == "orbit":
        cameras = orbit_cameras([c.scaled(capture.ratio) for c in capture.cameras], _pelvis(body_model, base), n_frames)
    elif kind != "path":
        cameras = [camera] * len(params)
    for k, (p, cam, frame) in enumerate(
        tqdm(list(zip(params, cameras, shown)), desc=f"video {kind}", unit="frame", disable=not progress)
    ):
        args = [torch.as_tensor(v)[None] for v in (p.poses, p.rh, p.th)]
        with torch.no_grad():
            if kind == "bones":
                factor = 1 + (r.scale - 1) * 0.5 * (1 - np.cos(2 * np.pi * k / max(len(params) - 1, 1)))
                rest = scaled_skeleton(body_model.rest_joints(shapes), LEG_JOINTS, float(factor))
                pose = pose_batch(posed_from_rest_joints(args[0], rigid_from_rotvec_translation(*args[1:]), rest))
            else:
                pose = pose_batch(body_model.pose_zju(*args, shapes))
            pose = run.colour_poses(pose, None if frame is None else [frame])  # docs/model.md §4
        frames_out.append(video_frame(to_numpy(render_view(field, cam, pose.to(r.device), config))))
    return write_mp4(out, frames_out, r.fps)


def path_views(run: LoadedRun, camera_path: Path | None, n_frames: int) -> tuple[list, list, list[int]]:
    """The capture parameters, cameras and capture frames of ``n_frames`` views along a camera path (checked against
    the capture)."""
    if camera_path is None:
        raise ValueError("--kind path renders a camera path: give --camera-path FILE (saved by narf-view)")
    path = read_camera_path(camera_path)
    for key in path.keyframes:
        if key.frame >= run.capture.n_frames:
            raise CaptureError(f"{camera_path}: frame {key.frame} is not a frame of {run.capture.root}")
    views = interpolate(path, n_frames)
    template = run.capture.cameras[0]
    cameras = [
        replace(
            template,
            name="path",
            K=intrinsics(path.width, path.height, v.fov_y_degrees),
            dist=np.zeros(5),
            cam_from_world=v.cam_from_world,
            width=path.width,
            height=path.height,
        )
        for v in views
    ]
    return [run.params(v.frame) for v in views], cameras, [v.frame for v in views]


def _report_motion(report: dict, path: Path) -> None:
    atomic_write_bytes(path, json.dumps(report, indent=1).encode())
    outside = [entry["frame"] for entry in report["out_of_range"]]
    if outside:
        worst = max((g, name) for entry in report["out_of_range"] for name, g in entry["parts"].items())
        print(
            f"narf-render-video: {len(outside)} of {report['frames']} frames leave the trained pose range (a part "
            f"> {report['threshold_degrees']:.0f} deg from every training pose; worst {worst[1]} {worst[0]} deg): "
            f"frames {_ranges(outside)}; details in {path}",
            file=sys.stderr,
        )


def _ranges(values: list[int]) -> str:
    """[1, 2, 3, 7] -> '1-3, 7'."""
    groups: list[list[int]] = []
    for value in values:
        if groups and value == groups[-1][1] + 1:
            groups[-1][1] = value
        else:
            groups.append([value, value])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in groups)


def _pelvis(body_model: BodyModel, params) -> np.ndarray:
    with torch.no_grad():
        body = body_model.pose_zju(
            *(torch.as_tensor(v)[None] for v in (params.poses, params.rh, params.th, params.shapes))
        )
    return body.world_from_joint[0, 0, :3, 3].numpy().astype(np.float64)
