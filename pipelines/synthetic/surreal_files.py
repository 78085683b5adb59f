"""Writer of SURREAL clips in exactly the generator's layout (``docs/formats.md §5``): the mp4, ``_info.mat``,
``_segm.mat`` and ``_depth.mat`` of one clip, from frames and annotations computed elsewhere.

``joints2D`` is computed as SURREAL's files hold it: the rounded projection of ``joints3D`` through K and the
det = -1 Blender extrinsics (``pipelines.datasets.surreal.surreal_cam_from_world``). Every file is written under
a temporary name and renamed, the video last but one and ``_info.mat`` last, so a clip whose ``_info.mat``
exists is complete.
"""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import scipy.io

from fitting.files import atomic_output
from pipelines.datasets.surreal import HEIGHT, SURREAL_K, WIDTH, surreal_cam_from_world


def project_joints(joints3d: np.ndarray, cam_loc: np.ndarray) -> np.ndarray:
    """round(K [R | t] X) for (T, 24, 3) world joints -> (T, 24, 2) pixels, SURREAL's ``joints2D``."""
    cam_from_world = surreal_cam_from_world(cam_loc)
    cam = joints3d @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    pixels = cam @ SURREAL_K.T
    return np.round(pixels[..., :2] / pixels[..., 2:])


def _savemat(path: Path, content: dict) -> None:
    with atomic_output(path) as tmp:  # .<stem>.partial.mat: savemat appends .mat to other names
        scipy.io.savemat(str(tmp), content, do_compression=True)


def write_surreal_clip(
    folder: str | Path,
    name: str,
    frames: np.ndarray,
    segm: np.ndarray,
    depth: np.ndarray,
    pose: np.ndarray,
    shape: np.ndarray,
    zrot: float,
    cam_loc: np.ndarray,
    joints3d: np.ndarray,
    gender: int,
    fps: int = 30,
) -> Path:
    """Write ``<folder>/<name>.mp4`` and its three ``.mat`` files; returns the ``_info.mat`` path.

    Args:
        frames: (T, 240, 320, 3) uint8 RGB. segm: (T, 240, 320) uint8 (0 background, p + 1 = joint p).
        depth: (T, 240, 320) float32 metres, 1e10 on the background.
        pose: (T, 72). shape: (10,) betas (constant in a clip). zrot: body rotation about z (radians).
        cam_loc: (3,) Blender camera location. joints3d: (T, 24, 3) world joints. gender: 0 female, 1 male.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    n = frames.shape[0]
    if frames.shape != (n, HEIGHT, WIDTH, 3) or segm.shape != (n, HEIGHT, WIDTH) or depth.shape != segm.shape:
        raise ValueError(f"frames/segm/depth: expected (T, {HEIGHT}, {WIDTH}[, 3]), got {frames.shape}, {segm.shape}")
    for kind, maps, dtype in (("segm", segm, np.uint8), ("depth", depth, np.float32)):
        _savemat(folder / f"{name}_{kind}.mat", {f"{kind}_{t + 1}": maps[t].astype(dtype) for t in range(n)})
    video = folder / f"{name}.mp4"
    with (
        atomic_output(video) as tmp_video,
        imageio.get_writer(tmp_video, fps=fps, codec="libx264", quality=8, macro_block_size=1) as writer,
    ):
        for frame in frames:
            writer.append_data(frame)
    cam_loc = np.asarray(cam_loc, dtype=np.float64).reshape(3, 1)
    info = {
        "pose": pose.T.astype(np.float32),
        "shape": np.repeat(np.asarray(shape, np.float32).reshape(10, 1), n, axis=1),
        "zrot": np.full((n, 1), zrot, dtype=np.float64),
        "camLoc": cam_loc,
        "camDist": np.array([[np.linalg.norm(cam_loc[:2])]]),
        "joints2D": project_joints(joints3d, cam_loc[:, 0]).transpose(2, 1, 0),
        "joints3D": joints3d.transpose(2, 1, 0),
        "gender": np.full((n, 1), gender, dtype=np.uint8),
        "sequence": name.rsplit("_c", 1)[0],
        "clipNo": np.array([[int(name.rsplit("_c", 1)[1]) if "_c" in name else 1]]),
        "stride": np.array([[1]]),
    }
    info_path = folder / f"{name}_info.mat"
    _savemat(info_path, info)
    return info_path
