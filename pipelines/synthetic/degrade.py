"""A capture broken the way real recordings are broken, where the truth is known (docs/guides/synthetic-data.md,
*Degraded captures*): every frame's body pose turned and moved (as a body fit from keypoints errs), and every camera's
colours scaled and offset (as unmatched cameras record them). The images, masks and cameras stay; the truth (the
source capture's poses, the cameras' gains and biases) is written to ``degraded.json``.

``degrade_capture(src, out, Degradation(...))`` writes into a hidden staging folder and renames it when complete."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from fitting.corrections import PoseCorrection
from fitting.files import write_image, write_npy, writes_folder
from narf.kinematics import N_JOINTS
from pipelines.body.model import BodyModel, capture_poses
from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.zju_mocap import SmplParams, param_index_from_image, write_params
from pipelines.synthetic.settings import Degradation  # noqa: F401 (re-exported)
from pipelines.synthetic.staging import link_into, publish, start_staging

TRUTH = "degraded.json"
FIELDS = ("poses", "rh", "th", "shapes")
#: what a degraded capture rewrites; everything else is linked from the source
REWRITTEN = ("params", "new_params", "vertices", "new_vertices", "synthetic.json")


def _turns(generator: torch.Generator, shape: tuple[int, ...], size: float) -> torch.Tensor:
    """(..., 3) vectors of length ``size`` along uniformly random directions."""
    axes = torch.randn(*shape, 3, generator=generator, dtype=torch.float64)
    return size * axes / axes.norm(dim=-1, keepdim=True)


def pose_noise(n_frames: int, degradation: Degradation) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The noise of ``degradation`` for frames 0..n-1 in ``fitting.corrections.PoseCorrection``'s terms (float64):
    joint turns (F, 23, 3), body turns (F, 3), shifts (F, 3). Drawn for one frame more than there are, as the
    corrections had one knot more than they used when this was written: the same seed gives the same noise."""
    generator = torch.Generator().manual_seed(degradation.seed)
    count = n_frames + 1
    joints = _turns(generator, (count, N_JOINTS - 1), np.radians(degradation.pose_degrees))
    root = _turns(generator, (count,), np.radians(degradation.pose_degrees))
    shift = _turns(generator, (count,), degradation.shift_m)
    return joints[:n_frames], root[:n_frames], shift[:n_frames]


def perturbed_params(capture: ZjuCapture, body: BodyModel, degradation: Degradation) -> list[SmplParams]:
    """Every frame's parameters with the pose noise of ``degradation`` (as :class:`fitting.corrections.PoseCorrection`
    applies a correction: joints turned in their parent's frame, the body about its pelvis). The correction that
    undoes it is the negated noise (:func:`pose_noise`) applied to the perturbed parameters."""
    frames = list(range(capture.n_frames))
    noise = PoseCorrection(capture_poses(capture, body, frames), centred=False).double()
    with torch.no_grad():
        for parameter, value in zip((noise.joints, noise.root, noise.shift), pose_noise(len(frames), degradation)):
            parameter.copy_(value)
    poses, rh, th = (v.float().numpy() for v in noise.zju_params())
    return [SmplParams(poses[f], rh[f], th[f], capture.params(f).shapes) for f in frames]


def camera_colours(n_cameras: int, spread: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Gains and biases (C, 3), each with mean identity over the cameras (log-gains and biases of mean zero)."""
    rng = np.random.default_rng(seed)
    log_gains = rng.uniform(-spread, spread, (n_cameras, 3))
    biases = rng.uniform(-spread / 4, spread / 4, (n_cameras, 3))
    return np.exp(log_gains - log_gains.mean(0)), biases - biases.mean(0)


def _recolour(capture: ZjuCapture, partial: Path, gains: np.ndarray, biases: np.ndarray, quality: int, progress):
    """Rewrite every image of camera c as ``clip(g_c I + b_c)`` (RGB), JPEG at ``quality``."""
    items = [(f, c) for f in range(capture.n_frames) for c in range(capture.n_cameras)]
    for frame, cam in tqdm(items, desc="recolouring", unit="image", disable=not progress):
        rel = capture.ims[frame][cam]
        bgr = cv2.imread(str(capture.root / rel), cv2.IMREAD_COLOR).astype(np.float32) / 255
        out = np.clip(bgr * gains[cam, ::-1] + biases[cam, ::-1], 0, 1)
        target = partial / rel
        target.unlink()  # a hard link to the source's file: never write through it
        # full-resolution colour (4:4:4): subsampling again would blur the colour the source already holds
        options = [
            cv2.IMWRITE_JPEG_QUALITY,
            quality,
            cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
            cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
        ]
        write_image(target, (out * 255 + 0.5).astype(np.uint8), options)


@writes_folder("out")
def degrade_capture(src: Path, out: Path, degradation: Degradation, progress: bool = True) -> Path:
    """Write ``out``: the capture ``src`` with its poses and camera colours broken (module docstring)."""
    degradation.validate()
    src, out = Path(src), Path(out)
    capture = ZjuCapture(src)
    body = BodyModel(dtype=torch.float64)
    partial = start_staging(out, "degraded", "degraded capture")
    for path in src.iterdir():
        if path.name not in REWRITTEN:
            link_into(path, partial / path.name)
    params = perturbed_params(capture, body, degradation)
    for folder, blend in (("params", False), ("new_params", True)):
        if not (src / folder).is_dir():
            continue
        (partial / folder).mkdir()
        (partial / folder.replace("params", "vertices")).mkdir()
        for frame, p in enumerate(params):
            index = param_index_from_image(capture.ims[frame][0])[1]
            write_params(partial / folder / f"{index}.npy", p)
            stack = [torch.as_tensor(np.asarray(getattr(p, k), np.float64)) for k in ("poses", "rh", "th", "shapes")]
            with torch.no_grad():
                vertices = body.pose_zju(*stack, pose_blendshapes=blend).vertices[0].numpy()
            write_npy(partial / folder.replace("params", "vertices") / f"{index}.npy", vertices.astype(np.float32))
    gains, biases = camera_colours(capture.n_cameras, degradation.colour_spread, degradation.seed)
    if degradation.colour_spread:
        source = json.loads((src / "synthetic.json").read_text()) if (src / "synthetic.json").is_file() else {}
        _recolour(capture, partial, gains, biases, source.get("config", {}).get("jpeg_quality", 95), progress)
    truth = {
        "source": str(src.resolve()),
        "degradation": asdict(degradation),
        "camera_gains": gains.round(6).tolist(),
        "camera_biases": biases.round(6).tolist(),
    }
    (partial / TRUTH).write_text(json.dumps(truth, indent=1))
    return publish(partial, out, {"dataset": "degraded", "truth": TRUTH})


def joint_errors(truth, source, body: BodyModel, frames: list[int]) -> np.ndarray:
    """(F,) mean distance (metres) over the 24 joints between ``source``'s poses (a capture, or a loaded run with its
    corrected poses) and ``truth``'s, per frame of ``frames``."""

    def joints(of) -> torch.Tensor:
        params = [of.params(f) for f in frames]
        stack = [torch.as_tensor(np.stack([getattr(p, k) for p in params]), dtype=body.dtype) for k in FIELDS]
        with torch.no_grad():
            return body.pose_zju(*stack).world_from_joint[..., :3, 3]

    return (joints(source) - joints(truth)).norm(dim=-1).mean(dim=-1).numpy()
