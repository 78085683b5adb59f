"""Any motion capture on a fitted subject (``docs/formats.md`` §7, ``docs/design.md`` *Driving the avatar*).

A motion is read into one form: per frame the root orientation (about the pelvis), the 23 joint rotations and the
pelvis position in the motion's own world, with its frame rate and up axis. It is then resampled to the video
rate (per-joint quaternion slerp, linear pelvis) and placed in the capture's world: the motion's up axis turned
onto the capture's, the body turned in the first frame to face where the training poses face, its start moved to
the centre of the training poses, and its lowest point over the clip set on the capture's floor. The subject
keeps its own shape; only the pose travels. The body faces where the training poses face rather than a camera
because NARF's pose input xi keeps the global orientation (docs/model.md §1): a body turned away from every
training pose is out of the trained range even when its joint angles are not.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from pipelines.body.model import BodyModel
from pipelines.body.surreal import surreal_world_pose
from pipelines.datasets.amass import read_amass
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.surreal import read_surreal_info
from pipelines.datasets.zju_mocap import SmplParams, read_params

#: Frame rate assumed for sources that do not store one (ZJU params folders); ``--motion-fps`` overrides it.
DEFAULT_FPS = 30.0
#: SURREAL renders CMU mocap (120 Hz) every 4th frame.
SURREAL_FPS = 30.0


@dataclass(frozen=True)
class Motion:
    """A motion in its own world.

    Attributes:
        source: what was read (file or folder) and its kind ('amass', 'zju', 'surreal').
        rotations: (T, 24, 3) axis-angle; [:, 0] is the root orientation in the motion's world (about the pelvis).
        pelvis: (T, 3) pelvis position in the motion's world (up to a constant offset, which placement removes).
        fps: frames per second.
        up: (3,) the world's up axis, or None to estimate it from the root orientations (SMPL's up is +y).
    """

    source: str
    rotations: np.ndarray
    pelvis: np.ndarray
    fps: float
    up: np.ndarray | None

    @property
    def n_frames(self) -> int:
        return self.rotations.shape[0]


def _zju_folder(folder: Path, rest_pelvis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    files = [p for p in folder.glob("*.npy") if p.stem.isdigit()]
    if not files:
        raise CaptureError(f"{folder}: no ZJU-MoCap params files (<frame>.npy)")
    params: list[SmplParams] = [read_params(p) for p in sorted(files, key=lambda p: int(p.stem))]
    rotations = np.stack([p.poses.reshape(24, 3) for p in params]).astype(np.float64)
    world_from_smpl = Rotation.from_rotvec(np.stack([p.rh for p in params]).astype(np.float64))
    # V = R(Rh) X + Th with X posed about the SMPL origin: the pelvis sits at R(Rh) J0 + Th
    rotations[:, 0] = (world_from_smpl * Rotation.from_rotvec(rotations[:, 0])).as_rotvec()
    pelvis = world_from_smpl.apply(rest_pelvis) + np.stack([p.th for p in params])
    return rotations, pelvis


def load_motion(path: str | Path, rest_pelvis: np.ndarray, fps: float | None = None) -> Motion:
    """Read an AMASS ``.npz``, a ZJU-MoCap ``params/`` or ``new_params/`` folder, or a SURREAL ``_info.mat``.

    Args:
        path: the motion file or folder.
        rest_pelvis: (3,) the subject's rest pelvis J0 (ZJU params rotate about the SMPL origin, not the pelvis).
        fps: the source frame rate, overriding the file's (needed for ZJU folders, which store none).
    """
    path = Path(path)
    if not path.exists():
        raise CaptureError(f"{path}: no such motion file or folder")
    if path.is_dir():
        rotations, pelvis = _zju_folder(path, np.asarray(rest_pelvis, np.float64))
        source, rate, up = f"{path} (ZJU-MoCap params)", DEFAULT_FPS, None
    elif path.suffix == ".npz":
        amass = read_amass(path)
        rotations, pelvis = amass.poses.reshape(-1, 24, 3), amass.trans
        source, rate, up = f"{path} (AMASS, {amass.gender or 'no gender'})", amass.fps, np.array([0.0, 0.0, 1.0])
    elif path.name.endswith("_info.mat"):
        clip = read_surreal_info(path)
        rotations = np.stack([surreal_world_pose(p, z) for p, z in zip(clip.pose, clip.zrot)]).reshape(-1, 24, 3)
        pelvis = clip.joints3d[:, 0].astype(np.float64)
        source, rate, up = f"{path} (SURREAL)", SURREAL_FPS, None  # up estimated from the body's orientation
    else:
        raise CaptureError(
            f"{path}: not a motion (expected an AMASS .npz, a SURREAL *_info.mat or a ZJU params/ folder)"
        )
    if fps is not None and not fps > 0:
        raise ValueError(f"motion frame rate must be positive, got {fps}")
    return Motion(source, np.asarray(rotations, np.float64), np.asarray(pelvis, np.float64), fps or rate, up)


def resample(motion: Motion, fps: float, start: int = 0, n_frames: int | None = None) -> Motion:
    """The motion at ``fps`` from source frame ``start``: rotations by per-joint slerp, the pelvis linearly.

    Output frame k lies at source time ``start / motion.fps + k / fps``; ``n_frames`` is clipped to the motion's end.
    """
    if not 0 <= start < motion.n_frames:
        raise ValueError(f"--start {start} is outside the motion's {motion.n_frames} frames")
    source_times = np.arange(motion.n_frames) / motion.fps
    available = int(np.floor((source_times[-1] - source_times[start]) * fps + 1e-9)) + 1
    count = available if n_frames is None else min(n_frames, available)
    times = source_times[start] + np.arange(count) / fps
    rotations = np.empty((count, 24, 3))
    for joint in range(24):
        if motion.n_frames == 1:
            rotations[:, joint] = motion.rotations[0, joint]
            continue
        slerp = Slerp(source_times, Rotation.from_rotvec(motion.rotations[:, joint]))
        rotations[:, joint] = slerp(np.clip(times, 0, source_times[-1])).as_rotvec()
    pelvis = np.stack([np.interp(times, source_times, motion.pelvis[:, d]) for d in range(3)], axis=1)
    return Motion(motion.source, rotations, pelvis, fps, motion.up)


def estimated_up(motion: Motion) -> np.ndarray:
    """The motion's up axis: declared, else the mean of R_root e_y (SMPL bodies stand along +y)."""
    if motion.up is not None:
        return motion.up / np.linalg.norm(motion.up)
    up = Rotation.from_rotvec(motion.rotations[:, 0]).apply([0.0, 1.0, 0.0]).mean(0)
    return up / np.linalg.norm(up)


def _flat(vector: np.ndarray, up: np.ndarray) -> np.ndarray:
    flat = vector - (vector @ up) * up
    norm = np.linalg.norm(flat)
    return flat / norm if norm > 1e-9 else flat


@dataclass(frozen=True)
class Stage:
    """Where a motion goes in the capture's world.

    Attributes:
        up: (3,) unit up axis. floor: height of the floor along ``up``. centre: (3,) where the motion starts
        (projected onto the floor). forward: (3,) the direction the body faces in the first frame.
    """

    up: np.ndarray
    floor: float
    centre: np.ndarray
    forward: np.ndarray


def stage_of(up: np.ndarray, vertices: np.ndarray, pelvis: np.ndarray, root_rotvecs: np.ndarray, floor=None) -> Stage:
    """The stage of a capture from its training poses: floor = their lowest vertex along ``up`` (or the capture's
    own ``floor``, whose up axis then replaces ``up``), centre = their mean pelvis, forward = their mean facing
    (SMPL's +z of the root, flattened onto the floor).

    Args:
        up: (3,) capture up axis. vertices: (F, V, 3) world vertices. pelvis: (F, 3). root_rotvecs: (F, 3) world
        root orientations. floor: a ``pipelines.datasets.floor.Floor`` or None.
    """
    if floor is not None:
        up, height = floor.up, floor.height
    else:
        up = up / np.linalg.norm(up)
        height = float((vertices @ up).min())
    facing = Rotation.from_rotvec(root_rotvecs).apply([0.0, 0.0, 1.0]).mean(0)
    return Stage(up, height, pelvis.mean(0), _flat(facing, up))


def place(motion: Motion, stage: Stage, body: BodyModel, shapes: np.ndarray) -> list[SmplParams]:
    """ZJU parameters of the subject (``shapes``) performing ``motion`` on ``stage`` (module docstring)."""
    # the smallest rotation taking the motion's up onto the stage's (a half turn when they are opposite)
    world_from_motion = Rotation.align_vectors(stage.up[None], estimated_up(motion)[None])[0]
    roots = Rotation.from_rotvec(motion.rotations[:, 0])
    forward = _flat(world_from_motion.apply(roots[0].apply([0.0, 0.0, 1.0])), stage.up)  # SMPL faces +z
    wanted = _flat(stage.forward, stage.up)
    if np.linalg.norm(forward) > 0 and np.linalg.norm(wanted) > 0:
        angle = np.arctan2(np.cross(forward, wanted) @ stage.up, forward @ wanted)
        world_from_motion = Rotation.from_rotvec(stage.up * angle) * world_from_motion
    rh = (world_from_motion * roots).as_rotvec()
    track = world_from_motion.apply(motion.pelvis - motion.pelvis[0])
    start = stage.centre - (stage.centre @ stage.up) * stage.up + stage.floor * stage.up
    rest_pelvis = body.rest_joints(torch.as_tensor(shapes, dtype=body.dtype)[None])[0, 0].double().numpy()
    poses = motion.rotations.reshape(-1, 72).copy()
    poses[:, :3] = 0
    th = start + track - Rotation.from_rotvec(rh).apply(rest_pelvis)
    lowest = min(
        float((_vertices(body, poses[i : i + 64], rh[i : i + 64], th[i : i + 64], shapes) @ stage.up).min())
        for i in range(0, len(poses), 64)
    )
    th = th + (stage.floor - lowest) * stage.up
    shapes32 = np.asarray(shapes, np.float32)
    return [
        SmplParams(p.astype(np.float32), r.astype(np.float32), t.astype(np.float32), shapes32)
        for p, r, t in zip(poses, rh, th)
    ]


def _vertices(body: BodyModel, poses, rh, th, shapes) -> np.ndarray:
    batch = len(poses)
    args = [torch.as_tensor(v, dtype=body.dtype) for v in (poses, rh, th, np.repeat(shapes[None], batch, 0))]
    with torch.no_grad():
        return body.pose_zju(*args).vertices.double().numpy().reshape(-1, 3)
