"""SURREAL clips: the reader against files written in SURREAL's exact layout, and its error cases."""

import imageio.v2 as imageio
import numpy as np
import pytest
import scipy.io

from pipelines.datasets.errors import CaptureError
from pipelines.datasets.surreal import (
    SURREAL_K,
    check_clip,
    read_frame_maps,
    read_surreal_info,
    right_handed_view,
    surreal_cam_from_world,
)
from pipelines.synthetic.surreal_files import write_surreal_clip

N_FRAMES = 4


def _clip(folder, name="01_01_c0001"):
    rng = np.random.default_rng(0)
    cam_loc = np.array([7.6, -1.0, 1.1])  # SURREAL: camera on +x at ~8 m, looking along -x at the person
    joints3d = np.array([0.0, -1.0, 1.0]) + rng.uniform(-0.6, 0.6, (N_FRAMES, 24, 3))
    segm = np.zeros((N_FRAMES, 240, 320), np.uint8)
    segm[:, 100:140, 150:170] = 7
    depth = np.where(segm > 0, 7.5, 1e10).astype(np.float32)
    frames = np.zeros((N_FRAMES, 240, 320, 3), np.uint8)
    frames[..., 0] = np.arange(N_FRAMES)[:, None, None] * 40
    pose, betas = rng.normal(0, 0.2, (N_FRAMES, 72)), rng.normal(0, 1, 10)
    info = write_surreal_clip(folder, name, frames, segm, depth, pose, betas, 0.7, cam_loc, joints3d, gender=1)
    return info, joints3d, cam_loc


def test_info_reads_frame_major_and_reprojects_joints2d(tmp_path):
    info_path, joints3d, cam_loc = _clip(tmp_path / "train" / "run0" / "01_01")
    raw = scipy.io.loadmat(str(info_path))
    assert raw["pose"].shape == (72, N_FRAMES) and raw["joints2D"].shape == (2, 24, N_FRAMES)  # as SURREAL stores
    clip = check_clip(info_path)
    assert clip.n_frames == N_FRAMES and clip.pose.shape == (N_FRAMES, 72) and clip.shape.shape == (N_FRAMES, 10)
    assert clip.joints2d.shape == (N_FRAMES, 24, 2) and clip.joints3d.shape == (N_FRAMES, 24, 3)
    # joints3D and zrot are stored as float64 and come back bit-exact; allclose's defaults are a formality
    assert np.allclose(clip.joints3d, joints3d) and (clip.gender == 1).all() and np.allclose(clip.zrot, 0.7)
    # the stored pose is float32: the reader returns it exactly as stored
    assert np.array_equal(clip.pose, raw["pose"].T.astype(np.float64))
    R, t = clip.cam_from_world[:3, :3], clip.cam_from_world[:3, 3]
    # Blender's mirrored camera, kept as it is; R has entries 0 and +-1, so det is exact
    assert np.linalg.det(R) == pytest.approx(-1.0, abs=1e-12)
    assert np.allclose(R, [[0, 0, -1], [0, 1, 0], [-1, 0, 0]]) and np.allclose(t, -R @ cam_loc)
    cam = clip.joints3d @ R.T + t
    assert (cam[..., 2] > 0).all()  # in front of the camera
    projected = (cam @ SURREAL_K.T)[..., :2] / (cam @ SURREAL_K.T)[..., 2:]
    assert np.array_equal(np.round(projected), clip.joints2d)  # round(K [R|t] joints3D) == joints2D, every joint
    # a proper rotation only fits the horizontally flipped image
    K_flip, proper = right_handed_view(clip.K, clip.cam_from_world)
    assert np.linalg.det(proper[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    cam_flip = clip.joints3d @ proper[:3, :3].T + proper[:3, 3]
    flipped = (cam_flip @ K_flip.T)[..., :2] / (cam_flip @ K_flip.T)[..., 2:]
    # float64 projections of the same points: rounding ~1e-13 px
    assert np.allclose(flipped[..., 0], 319 - projected[..., 0], atol=1e-9)
    assert np.allclose(flipped[..., 1], projected[..., 1], atol=1e-9)


def test_frame_maps_use_one_based_keys(tmp_path):
    info_path, _, _ = _clip(tmp_path)
    segm, depth = read_frame_maps(info_path, 0)
    assert segm.dtype == np.uint8 and segm.shape == (240, 320) and segm[120, 160] == 7 and segm[0, 0] == 0
    assert depth[0, 0] == np.float32(1e10) and depth[120, 160] == np.float32(7.5)
    with pytest.raises(CaptureError, match="no 'segm_5' \\(frame 4; keys are 1-based\\)"):
        read_frame_maps(info_path, N_FRAMES)


def test_bad_clips_name_the_file(tmp_path):
    info_path, _, _ = _clip(tmp_path / "short")
    with imageio.get_writer(tmp_path / "short" / "01_01_c0001.mp4", fps=30, macro_block_size=1) as writer:
        for _ in range(N_FRAMES - 1):
            writer.append_data(np.zeros((240, 320, 3), np.uint8))
    with pytest.raises(CaptureError, match=f"01_01_c0001.mp4: {N_FRAMES - 1} frames, but .* annotates {N_FRAMES}"):
        check_clip(info_path)
    info = scipy.io.loadmat(str(info_path))
    del info["camLoc"]
    broken = tmp_path / "broken_info.mat"
    scipy.io.savemat(str(broken), {k: v for k, v in info.items() if not k.startswith("__")})
    with pytest.raises(CaptureError, match="broken_info.mat: missing keys \\['camLoc'\\]"):
        read_surreal_info(broken)
    garbage = tmp_path / "garbage_info.mat"
    garbage.write_bytes(b"not a mat file")
    with pytest.raises(CaptureError, match="garbage_info.mat: not a readable MATLAB file"):
        read_surreal_info(garbage)
    with pytest.raises(CaptureError, match="no such SURREAL"):
        read_surreal_info(tmp_path / "missing_info.mat")


def test_cam_from_world_maps_the_camera_location_to_the_origin():
    cam_from_world = surreal_cam_from_world(np.array([8.0, -1.0, 1.2]))
    # R has entries 0 and +-1: the products are exact
    assert np.allclose(cam_from_world[:3, :3] @ [8.0, -1.0, 1.2] + cam_from_world[:3, 3], 0.0)
