"""Videos of an autoencoder run (``narf-render-video --run RUN --input ...``): encode one image of a person and
render that person in an orbit or in other poses, or morph the codes of two people.

An input is a NARF ``render_128`` colour PNG (its ``pose_to_world_*.npy`` and ``pose_to_camera_*.npy`` beside
it) or a SURREAL clip's ``_info.mat`` with an optional ``:FRAME`` (default 0); its pose and camera come with it.
A plain photograph has no skeleton to render, so it is refused with a line saying what to give instead.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import torch
from tqdm import tqdm

from fitting.autoencoder import encode
from fitting.evaluate import render_view
from fitting.fitted import SavedRun, run_folder
from fitting.plots import to_numpy
from fitting.video import video_frame, write_mp4
from narf.kinematics import rest_offsets_from_world, retarget
from pipelines.body.model import BodyModel, pose_batch_from_joints
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.surreal import check_clip
from pipelines.datasets.thuman import read_render
from pipelines.runs.autoencoder.evaluation import (
    AutoencoderRun,
    check_refinable,
    load_autoencoder_run,
    refined_code,
    surreal_view,
)
from pipelines.runs.autoencoder.session import ThumanView, load_views, view_of_render
from pipelines.runs.requests import VideoRequest, refuse_options
from pipelines.synthetic.scene import look_at

AUTOENCODER_VIDEO_KINDS = ("orbit", "poses", "interpolate")
_RENDER_NAME = re.compile(r"^color_(\d{8})\.png$")


@dataclass
class EncodedInput:
    """One input: its 128^2 view (image on black, camera), joint frames (1, 24, 4, 4) and encoder image."""

    view: ThumanView
    world_from_joint: torch.Tensor
    image_u8: torch.Tensor


def read_input(spec: str, body_model: BodyModel) -> EncodedInput:
    """A render_128 colour PNG or ``<clip>_info.mat[:FRAME]`` (module docstring)."""
    path_text, _, frame_text = spec.partition(".mat:")
    if frame_text or spec.endswith("_info.mat"):
        info = Path(path_text + ".mat" if frame_text else spec)
        frame = int(frame_text) if frame_text.isdigit() else 0
        clip = check_clip(info)
        if not 0 <= frame < clip.n_frames:
            raise CaptureError(f"{info}: frame {frame} outside 0..{clip.n_frames - 1}")
        with imageio.get_reader(str(info).replace("_info.mat", ".mp4")) as video:
            view, pose = surreal_view(clip, info, frame, body_model, video)
        joints = pose.world_from_joint
    else:
        path = Path(spec)
        match = _RENDER_NAME.match(path.name)
        if not path.is_file():
            raise CaptureError(f"{path}: no such input image")
        if match is None:
            raise CaptureError(
                f"{path}: an image without a skeleton; give a render_128 color_XXXXXXXX.png (pose_to_world beside it) "
                "or a SURREAL <clip>_info.mat[:FRAME]"
            )
        render = read_render(path.parent, int(match[1]), renders_per_mesh=1)
        view = view_of_render(render, path.name)
        joints = torch.as_tensor(render.pose_to_world[None], dtype=torch.float32)
    image = torch.as_tensor(np.uint8(view.image * 255 + 0.5).transpose(2, 0, 1))[None]
    return EncodedInput(view, joints.float(), image)


def _orbit(view: ThumanView, joints: torch.Tensor, n_frames: int) -> list:
    """Cameras circling the body about its own up axis (pelvis -> neck) at the input camera's distance."""
    positions = joints[0, :, :3, 3].double().numpy()
    centre = positions.mean(axis=0)
    up = positions[12] - positions[0]
    up /= np.linalg.norm(up)
    rotation = view.camera.cam_from_world[:3, :3]
    eye = -rotation.T @ view.camera.cam_from_world[:3, 3]
    offset = eye - centre
    height = offset @ up
    start = offset - height * up
    radius = np.linalg.norm(start)
    start /= radius
    side = np.cross(up, start)
    out = []
    for k in range(n_frames):
        angle = 2 * np.pi * k / n_frames
        position = centre + radius * (np.cos(angle) * start + np.sin(angle) * side) + height * up
        out.append(replace(view.camera, cam_from_world=look_at(position, centre, down=-up)))
    return out


def _motion(run: AutoencoderRun, n_frames: int) -> torch.Tensor:
    """Joint frames of the set's held-out poses (same_view renders of novel-pose meshes), (F, 24, 4, 4)."""
    meshes = list(range(run.dataset.n_train_meshes, run.dataset.n_meshes)) or list(range(run.dataset.n_meshes))
    _, _, poses = load_views(run.dataset, "same_view", meshes[:n_frames], progress=False)
    return poses.world_from_joint


def render_autoencoder_video(run: Path | SavedRun, request: VideoRequest) -> Path:
    """Render ``request.kind`` for the encoded ``request.inputs`` to an mp4 of input | RGB | depth | segmentation;
    ``refine_steps`` > 0 refines each code on its input first (``fitting.autoencoder.refine_code``). The kind table's
    entry point: options of subject runs are refused."""
    r = request
    run_dir = run_folder(run)
    options = {
        "--motion": r.motion,
        "--camera": r.camera is not None,
        "--start": r.start,
        "--motion-fps": r.motion_fps,
        "--samples": r.samples,
    }
    refuse_options(run_dir, "autoencoder", options, "subject runs")
    kind, inputs, n_frames, device, refine_steps = r.kind, list(r.inputs), r.frames, r.device, r.refine_steps
    if kind not in AUTOENCODER_VIDEO_KINDS:
        raise ValueError(f"an autoencoder run renders --kind {', '.join(AUTOENCODER_VIDEO_KINDS)}, not '{kind}'")
    needed = 2 if kind == "interpolate" else 1
    if len(inputs) != needed:
        raise ValueError(f"--kind {kind} takes {needed} --input, got {len(inputs)}")
    run = load_autoencoder_run(run, device)
    check_refinable(run, run_dir, refine_steps)
    body_model = BodyModel()
    items = [read_input(spec, body_model) for spec in inputs]
    with torch.no_grad():
        codes = [encode(run.encoder, item.image_u8.to(device)) for item in items]
    if refine_steps:
        poses = [pose_batch_from_joints(item.world_from_joint.double()).to(torch.float32) for item in items]
        codes = [refined_code(run, z, item.view, p, refine_steps, device) for z, item, p in zip(codes, items, poses)]
    first = items[0]
    rest = rest_offsets_from_world(first.world_from_joint)
    image = lambda item: item.view.image  # noqa: E731
    if kind == "orbit":
        cameras = _orbit(first.view, first.world_from_joint, n_frames)
        plan = [(cam, first.world_from_joint, codes[0], image(first)) for cam in cameras]
    elif kind == "poses":
        motion = _motion(run, n_frames)
        retargeted = retarget(motion, rest.expand(motion.shape[0], 24, 3))
        plan = [(first.view.camera, retargeted[k : k + 1], codes[0], image(first)) for k in range(motion.shape[0])]
    else:  # the first input's pose and camera; codes (and the input tile) blend from the first to the second
        blend = lambda w: (
            first.view.camera,
            first.world_from_joint,
            (1 - w) * codes[0] + w * codes[1],  # noqa: E731
            (1 - w) * image(first) + w * image(items[1]),
        )
        plan = [blend(w) for w in np.linspace(0, 1, n_frames)]
    frames = []
    for camera, joints, code, tile in tqdm(plan, desc=f"video {kind}", unit="frame", disable=not r.progress):
        pose = pose_batch_from_joints(joints.double()).to(torch.float32)
        with torch.no_grad():
            render = to_numpy(render_view(run.field, camera, pose.to(device), run.config, code))
        frames.append(np.concatenate([(np.clip(tile, 0, 1) * 255 + 0.5).astype(np.uint8), video_frame(render)], axis=1))
    return write_mp4(r.out, frames, r.fps)
