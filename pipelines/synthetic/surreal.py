"""A SURREAL-like set in SURREAL's layout (``docs/formats.md §5``), from the stand-in body: unclothed people of a
wide range of body sizes, moving smoothly in front of SURREAL's fixed camera at SURREAL's distance
(camDist ~ N(8, 1) m), rendered at 320 x 240 with segmentation and depth.

The body is placed as SURREAL places it: the stored ``pose[0:3]`` already turns the y-up SMPL body into the
z-up mocap frame, the world orientation is R_x(pi/2) R_z(zrot) R(pose[0:3]) and the pelvis follows ``joints3D``
(``docs/formats.md §5.4``; ``pipelines.body.surreal``, which re-poses the body from ``_info.mat`` onto
``_segm.mat``).
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from fitting.files import writes_folder
from pipelines.body.model import BodyModel
from pipelines.body.surreal import R_X90, surreal_world_pose
from pipelines.datasets.surreal import HEIGHT, SURREAL_K, WIDTH, surreal_cam_from_world
from pipelines.synthetic.people import person_colours, random_person, random_poses, raycast
from pipelines.synthetic.settings import SurrealSynthConfig  # noqa: F401 (re-exported)
from pipelines.synthetic.staging import is_finished, publish, start_staging
from pipelines.synthetic.surreal_files import write_surreal_clip

SURREAL_VERSION = 1


def smooth_motion(n_frames: int, rng: np.random.Generator, n_keys: int = 4) -> np.ndarray:
    """(n_frames, 72) body poses interpolated (cosine ease) between random key poses; global orientation 0."""
    keys = random_poses(n_keys, rng)
    position = np.linspace(0, n_keys - 1, n_frames)
    low = np.minimum(np.floor(position).astype(int), n_keys - 2)
    weight = (1 - np.cos(np.pi * (position - low))) / 2
    return keys[low] * (1 - weight[:, None]) + keys[low + 1] * weight[:, None]


def _background(rng: np.random.Generator) -> np.ndarray:
    """A smooth random colour field with a few soft blobs, (240, 320, 3) in [0, 1] (SURREAL pastes LSUN photos)."""
    ys, xs = np.mgrid[0:HEIGHT, 0:WIDTH] / np.array(WIDTH, np.float64)
    image = rng.uniform(0.2, 0.8, 3) + (xs[..., None] - 0.5) * rng.uniform(-0.4, 0.4, 3)
    for _ in range(6):
        centre, radius = rng.uniform([0, 0], [1, 0.75]), rng.uniform(0.05, 0.25)
        blob = np.exp(-((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) / radius**2)
        image += blob[..., None] * rng.uniform(-0.3, 0.3, 3)
    return np.clip(image, 0, 1)


def _clip_poses(config: SurrealSynthConfig, rng: np.random.Generator) -> tuple[np.ndarray, float, np.ndarray]:
    """Stored poses (T, 72) with SURREAL's z-up root, zrot, and pelvis positions (T, 3) in the world."""
    poses = smooth_motion(config.frames, rng)
    yaw = rng.uniform(-0.3, 0.3) + np.linspace(0, rng.uniform(-0.5, 0.5), config.frames)
    for t in range(config.frames):  # the mocap root: SMPL y-up turned z-up, then a slow turn about the new up
        root = cv2.Rodrigues(np.array([0.0, 0.0, yaw[t]]))[0] @ R_X90
        poses[t, :3] = cv2.Rodrigues(root)[0].ravel()
    start = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-1.3, -0.7), rng.uniform(-0.4, 0.4)])
    walk = np.outer(np.linspace(0, 1, config.frames), [rng.uniform(-0.6, 0.6), 0.0, rng.uniform(-0.6, 0.6)])
    return poses, float(rng.uniform(-np.pi, np.pi)), start + walk


def _render_clip(body: BodyModel, config: SurrealSynthConfig, rng: np.random.Generator) -> dict:
    person = random_person(rng, clothed=False, beta_std=config.beta_std)
    betas = torch.as_tensor(person.betas, dtype=torch.float32)[None]
    weights = body.smpl.lbs_weights.numpy()
    colours = person_colours(person, body.rest_body(betas).vertices[0].numpy(), weights)
    labels = (weights.argmax(axis=1) + 1).astype(np.uint8)  # SURREAL: p + 1 = SMPL joint p
    poses, zrot, pelvis = _clip_poses(config, rng)
    world = np.stack([surreal_world_pose(pose, zrot) for pose in poses])
    j0 = body.rest_joints(betas)[0, 0].numpy()
    posed = body.pose_zju(
        torch.as_tensor(world, dtype=torch.float32),
        torch.zeros(config.frames, 3),
        torch.as_tensor(pelvis - j0, dtype=torch.float32),
        betas.expand(config.frames, 10),
    )
    cam_loc = np.array([np.clip(rng.normal(8.0, 1.0), 6.0, 10.5), -1.0, 0.0])
    cam_from_world = surreal_cam_from_world(cam_loc)
    lights = [(np.array([0.5, -0.7, 0.4]), 0.55), (np.array([0.8, 0.1, -0.6]), 0.3)]
    background = _background(rng)
    out = {k: [] for k in ("frames", "segm", "depth")}
    for t in range(config.frames):
        render = raycast(
            posed.vertices[t].double().numpy(),
            body.faces,
            colours,
            labels,
            SURREAL_K,
            cam_from_world,
            WIDTH,
            HEIGHT,
            lights,
            ambient=0.35,
        )
        alpha = render["alpha"][..., None]
        out["frames"].append(np.uint8(np.clip(render["rgb"] + (1 - alpha) * background, 0, 1) * 255 + 0.5))
        out["segm"].append(render["labels"])
        out["depth"].append(np.where(render["labels"] > 0, render["depth"], 1e10).astype(np.float32))
    joints3d = posed.world_from_joint[:, :, :3, 3].double().numpy()
    out = {k: np.stack(v) for k, v in out.items()}
    gender = 0 if person.gender == "female" else 1
    return dict(out, pose=poses, shape=person.betas, zrot=zrot, cam_loc=cam_loc, joints3d=joints3d, gender=gender)


def is_surreal_complete(out: Path, config: SurrealSynthConfig | None = None) -> bool:
    """True when ``out`` holds a finished SURREAL-like set (with these settings, if ``config`` is given)."""
    return is_finished(out, "surreal", config, SURREAL_VERSION)


@writes_folder()
def generate_surreal(
    out: str | Path, config: SurrealSynthConfig = SurrealSynthConfig(), smpl_path=None, progress: bool = True
) -> Path:
    """Generate (or reuse) the SURREAL-like set at ``out`` (clips under ``<out>/<split>/run0/``)."""
    config.validate()
    out = Path(out)
    if is_surreal_complete(out, config):
        return out
    partial = start_staging(out, "surreal", "SURREAL-like set")
    body = BodyModel(smpl_path)
    infos = []
    for clip in tqdm(range(config.clips), desc="surreal clips", unit="clip", disable=not progress):
        data = _render_clip(body, config, np.random.default_rng([config.seed, clip]))
        seq = f"syn{clip + 1:02d}_01"
        folder = partial / config.split / "run0" / seq
        info = write_surreal_clip(
            folder,
            f"{seq}_c0001",
            data["frames"],
            data["segm"],
            data["depth"],
            data["pose"],
            data["shape"],
            data["zrot"],
            data["cam_loc"],
            data["joints3d"],
            data["gender"],
        )
        infos.append(str(info.relative_to(partial)))
    marker = {"dataset": "surreal", "version": SURREAL_VERSION, "config": asdict(config), "clips": infos}
    return publish(partial, out, marker)
