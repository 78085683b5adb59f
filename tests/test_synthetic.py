import hashlib
import json
import os

import cv2
import numpy as np
import pytest
import torch

from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.easymocap import read_easymocap_cameras
from pipelines.datasets.zju_mocap import read_annots
from pipelines.synthetic.capture import SynthConfig, generate_capture, is_complete


def _rasterise(vertices, faces, camera_K, dist, rvec, tvec, size):
    pts = cv2.projectPoints(vertices.astype(np.float64), rvec, tvec, camera_K, dist)[0][:, 0]
    # fillPoly also covers pixels that an edge merely touches: rasterise at 9x and keep each block's centre
    # (pixel centres at integer coordinates map to 9u + 4), which tests pixel-centre coverage.
    scale, shift = 9, 4
    mask = np.zeros((size * scale, size * scale), np.uint8)
    polys = np.round((pts[faces] * scale + (scale - 1) / 2) * (1 << shift)).astype(np.int32)
    for poly in polys:  # one call per triangle: fillPoly with many contours fills by parity
        cv2.fillConvexPoly(mask, poly, 1, lineType=cv2.LINE_8, shift=shift)
    return mask[scale // 2 :: scale, scale // 2 :: scale].astype(bool)


def test_projected_vertices_reproduce_masks(tiny_capture, body_model):
    annots = np.load(tiny_capture / "annots.npy", allow_pickle=True).item()
    cams = annots["cams"]
    ious = []
    for frame in range(4):
        vertices = np.load(tiny_capture / "new_vertices" / f"{frame}.npy")
        for c in range(4):
            R, T = np.array(cams["R"][c]), np.array(cams["T"][c]) / 1000.0
            rendered = cv2.imread(
                str(tiny_capture / "mask" / annots["ims"][frame]["ims"][c].replace(".jpg", ".png")),
                cv2.IMREAD_UNCHANGED,
            ).astype(bool)
            projected = _rasterise(
                vertices, body_model.faces, np.array(cams["K"][c]), np.array(cams["D"][c]), cv2.Rodrigues(R)[0], T, 256
            )
            ious.append((rendered & projected).sum() / (rendered | projected).sum())
    assert min(ious) >= 0.98, ious


def test_neuralbody_style_reading(tiny_capture):
    """Replicates neuralbody multi_view_dataset's reads: annots, image path, mask_cihp, params, vertices."""
    annots = np.load(os.path.join(tiny_capture, "annots.npy"), allow_pickle=True).item()
    cams = annots["cams"]
    assert len(cams["K"]) == 4 and np.array(cams["T"][0]).shape == (3, 1) and np.array(cams["D"][0]).shape == (5, 1)
    ims = np.array([np.array(d["ims"])[[0, 1]] for d in annots["ims"][0:4][::1]]).ravel()
    img_path = os.path.join(tiny_capture, ims[3])
    img = cv2.imread(img_path)
    assert img.shape == (256, 256, 3)
    msk = cv2.imread(os.path.join(tiny_capture, "mask_cihp", ims[3])[:-4] + ".png", cv2.IMREAD_UNCHANGED)
    assert msk.shape == (256, 256) and set(np.unique(msk)) >= {0, 2, 5, 9, 13}  # hair, shirt, pants, face
    i = int(os.path.basename(img_path)[:-4])
    params = np.load(os.path.join(tiny_capture, "params", f"{i}.npy"), allow_pickle=True).item()
    assert params["poses"].shape == (1, 72) and params["Rh"].shape == (1, 3) and params["shapes"].shape == (1, 10)
    xyz = np.load(os.path.join(tiny_capture, "vertices", f"{i}.npy"))
    R = cv2.Rodrigues(params["Rh"])[0].astype(np.float32)
    smpl_frame = np.dot(xyz - params["Th"].astype(np.float32), R)
    assert np.abs(smpl_frame).max() < 2.0  # body-sized in the SMPL frame
    centre = -np.array(cams["R"][0]).T @ np.array(cams["T"][0]) / 1000.0
    assert 2.5 < np.hypot(centre[0, 0], centre[1, 0]) < 3.5 and -2.1 < centre[2, 0] < -1.7  # z-down ring


def test_params_reproduce_vertices(tiny_capture, body_model64):
    cap = ZjuCapture(tiny_capture)
    for frame in (0, 3):
        p = cap.params(frame)
        args = [torch.as_tensor(v, dtype=torch.float64) for v in (p.poses, p.rh, p.th, p.shapes)]
        new = body_model64.pose_zju(*args).vertices[0].numpy()
        old = body_model64.pose_zju(*args, pose_blendshapes=False).vertices[0].numpy()
        # the vertex files are float32 (half an ulp at 2 m: 1.2e-7) and were posed in float32 (~1e-6 m after a
        # few dozen operations); 1e-5 m is far below a convention error (~0.1 m)
        assert np.abs(new - np.load(tiny_capture / "new_vertices" / f"{frame}.npy")).max() < 1e-5
        assert np.abs(old - np.load(tiny_capture / "vertices" / f"{frame}.npy")).max() < 1e-5
        assert np.abs(new - old).max() > 1e-3  # pose blend shapes are not trivial
        assert new[:, 2].max() == pytest.approx(0.0, abs=1e-5)  # feet on the floor, z down (float32 files, as above)


def test_easymocap_cameras_match_annots(tiny_capture):
    cameras, _ = read_annots(tiny_capture / "annots.npy")
    easy = read_easymocap_cameras(tiny_capture)
    assert [c.name for c in easy] == [c.name for c in cameras]
    for a, b in zip(cameras, easy):
        # both written from the same float64 cameras; OpenCV's YAML keeps 16 significant digits and annots R is
        # re-orthonormalised (SVD, ~1e-15), the Rodrigues round trip costs ~1e-15
        assert np.allclose(a.K, b.K) and np.allclose(a.dist, b.dist)
        assert np.allclose(a.cam_from_world, b.cam_from_world, atol=1e-9)
        assert (b.width, b.height) == (256, 256)


def test_calibration_shots_detectable(tiny_capture):
    from pipelines.calibration.board import BoardSpec

    spec = json.loads((tiny_capture / "calib" / "board.json").read_text())
    board = BoardSpec(
        **{k: spec[k] for k in ("squares_x", "squares_y", "square_length", "marker_length", "dictionary")}
    ).board()
    detector = cv2.aruco.CharucoDetector(board)
    cameras, _ = read_annots(tiny_capture / "annots.npy")
    truth = np.load(tiny_capture / "calib" / "ground_truth.npz")
    shots = [(cam, f"{shot:03d}.jpg", pose) for cam in cameras for shot, pose in enumerate(truth["world_from_board"])]
    shots += [
        (cam, f"intrinsics/{k:03d}.jpg", pose)
        for c, cam in enumerate(cameras)
        for k, pose in enumerate(truth["close_world_from_board"][c])
    ]
    found, close_found = 0, 0
    for cam, name, pose in shots:
        image = cv2.imread(str(tiny_capture / "calib" / cam.name / name), cv2.IMREAD_GRAYSCALE)
        corners, ids, _, _ = detector.detectBoard(image)
        if ids is None or len(ids) < 6:
            continue
        found += 1
        close_found += name.startswith("intrinsics")
        object_points = board.getChessboardCorners()[ids.ravel()]
        world = object_points @ pose[:3, :3].T + pose[:3, 3]
        rvec = cv2.Rodrigues(cam.cam_from_world[:3, :3])[0]
        projected = cv2.projectPoints(world, rvec, cam.cam_from_world[:3, 3], cam.K, cam.dist)[0][:, 0]
        assert np.abs(projected - corners.reshape(-1, 2)).max() < 1.0, name  # corners sit where the truth projects
    assert found >= 1 and close_found >= len(cameras)  # close-ups fill the frame: nearly always detected


def test_generation_is_deterministic_and_reused(tmp_path):
    config = SynthConfig(resolution=48, frames=2, cameras=2, calib_shots=0, workers=1)
    a = generate_capture(tmp_path / "a", config, progress=False)
    b = generate_capture(tmp_path / "b", config, progress=False)
    digest = lambda p: hashlib.md5(p.read_bytes()).hexdigest()  # noqa: E731
    for rel in ("Camera_B2/000001.jpg", "mask_cihp/Camera_B1/000000.png", "new_params/1.npy", "annots.npy"):
        assert digest(a / rel) == digest(b / rel)
    assert is_complete(a, config)
    mtime = (a / "annots.npy").stat().st_mtime
    generate_capture(a, config, progress=False)
    assert (a / "annots.npy").stat().st_mtime == mtime  # reused, not regenerated
    assert not list(tmp_path.glob(".*.partial"))


def test_generation_refuses_foreign_folder_and_bad_config(tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="not empty"):
        generate_capture(tmp_path / "mine", SynthConfig(resolution=48, frames=1, cameras=1, calib_shots=0))
    (tmp_path / "file").write_text("")
    with pytest.raises(FileExistsError, match="not a folder"):
        generate_capture(tmp_path / "file", SynthConfig(resolution=48, frames=1, cameras=1, calib_shots=0))
    with pytest.raises(ValueError, match="layout"):
        generate_capture(tmp_path / "x", SynthConfig(layout="weird"))


def test_closest_surface_points_match_trimesh(body_model):
    import trimesh

    from fitting.mesh import closest_surface_points
    from pipelines.synthetic.lbs import grid_points

    vertices = body_model.rest_body(torch.zeros(1, 10)).vertices[0].double().numpy()
    points = grid_points(vertices).reshape(-1, 3)
    points = points[np.random.default_rng(0).choice(len(points), 1500, replace=False)]
    _, exact, _ = trimesh.proximity.closest_point(trimesh.Trimesh(vertices, body_model.faces, process=False), points)
    _, ours, _ = closest_surface_points(vertices, body_model.faces, points)
    # the same point-triangle projection by two formulae (float64): 1e-6 m is far below a wrong-triangle error,
    # which is a sizeable fraction of an edge (~1 cm with the nearest vertex alone)
    np.testing.assert_allclose(ours, exact, atol=1e-6)


def test_animatable_nerf_lbs_folder(tmp_path, body_model):
    from pipelines.synthetic.lbs import BOX_PADDING, VOXEL

    root = generate_capture(
        tmp_path / "cap",
        SynthConfig(resolution=48, frames=2, cameras=2, calib_shots=0, workers=1, lbs=True),
        progress=False,
    )
    lbs = root / "lbs"
    assert np.load(lbs / "joints.npy").shape == (24, 3) and np.load(lbs / "parents.npy")[0] == 4294967295
    assert np.load(lbs / "weights.npy").shape == (6890, 24) and np.load(lbs / "faces.npy").shape == (13776, 3)
    tpose = np.load(lbs / "tvertices.npy").astype(np.float64)
    tbw = np.load(lbs / "tbw.npy")
    # the grid samples of upstream's prepare_blend_weights: np.arange(low, high + voxel, voxel) per axis
    low, high = tpose.min(0) - BOX_PADDING, tpose.max(0) + BOX_PADDING
    assert tbw.shape == (*[len(np.arange(low[d], high[d] + VOXEL, VOXEL)) for d in range(3)], 25)
    assert all(low[d] + (tbw.shape[d] - 1) * VOXEL >= high[d] - 1e-9 for d in range(3))
    # tvertices: frame 0 un-posed by inverse LBS = the shaped template plus frame 0's pose correctives
    p0 = np.load(root / "new_params" / "0.npy", allow_pickle=True).item()
    smpl = body_model.smpl
    rot = torch.as_tensor(np.stack([cv2.Rodrigues(r)[0] for r in p0["poses"].reshape(24, 3)]))
    correctives = ((rot[1:] - torch.eye(3, dtype=rot.dtype)).reshape(1, -1).float() @ smpl.posedirs).reshape(-1, 3)
    shaped = smpl.v_template + (smpl.shapedirs @ torch.as_tensor(p0["shapes"][0]).float())
    # float32 skinning of 24 transforms and its float64 inverse of a float32 vertex file: ~1e-6 m
    np.testing.assert_allclose(tpose, (shaped + correctives).numpy(), atol=2e-5)
    # bigpose_vertices: plain LBS (no correctives) of tvertices with the hips turned +-30 deg about z: vertices
    # skinned to the pelvis alone stay put; those skinned to the left knee alone turn about the left hip
    big = np.load(lbs / "bigpose_vertices.npy").astype(np.float64)
    weights = np.load(lbs / "weights.npy")
    joints = np.load(lbs / "joints.npy").astype(np.float64)
    pelvis, knee = weights[:, 0] > 1 - 1e-6, weights[:, 4] > 1 - 1e-6
    assert pelvis.sum() > 10 and knee.sum() > 10
    np.testing.assert_allclose(big[pelvis], tpose[pelvis], atol=1e-5)  # float32 storage of ~1 m values
    turn = cv2.Rodrigues(np.array([0.0, 0.0, np.deg2rad(30)]))[0]
    np.testing.assert_allclose(big[knee], (tpose[knee] - joints[1]) @ turn.T + joints[1], atol=1e-5)
    # the nearest grid sample to a surface point lies within half a voxel diagonal of the surface
    index = np.round((tpose[0] - low) / VOXEL).astype(int)
    cell = tbw[tuple(index)]
    # the grid is float32: distances ~0.02 m to 1e-9, and 24 float32 weights summing to 1 to ~24 eps32 ~ 3e-6
    assert cell[24] <= VOXEL * np.sqrt(3) / 2 + 1e-6 and np.isclose(cell[:24].sum(), 1, atol=1e-5)
    frame = np.load(lbs / "bweights" / "1.npy")
    assert frame.ndim == 4 and frame.shape[3] == 25
    params = np.load(lbs / "smpl_params.npy", allow_pickle=True).item()
    assert params["poses"].shape == (2, 72)
    # posed grids are in the SMPL frame: R(Rh)^T (v - Th) of new_vertices
    p = np.load(root / "new_params" / "1.npy", allow_pickle=True).item()
    smpl_frame = (np.load(root / "new_vertices" / "1.npy") - p["Th"]) @ cv2.Rodrigues(p["Rh"])[0]
    low, high = smpl_frame.min(0) - BOX_PADDING, smpl_frame.max(0) + BOX_PADDING
    assert frame.shape[:3] == tuple(len(np.arange(low[d], high[d] + VOXEL, VOXEL)) for d in range(3))
