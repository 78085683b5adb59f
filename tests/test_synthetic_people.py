"""The THUman- and SURREAL-like stand-ins, read back through the readers of the real formats."""

import json
import re

import numpy as np
import pytest
import torch

from pipelines.body.surreal import pose_surreal
from pipelines.datasets.surreal import check_clip, read_frame_maps
from pipelines.datasets.thuman import (
    THUMAN_K,
    count_renders,
    read_colored_obj,
    read_render,
    read_smpl_params_txt,
)
from pipelines.synthetic.people import SWIMWEAR_SHARE, person_colours, random_person, raycast
from pipelines.synthetic.surreal import SurrealSynthConfig, generate_surreal
from pipelines.synthetic.thuman import ThumanSynthConfig, generate_thuman, is_thuman_complete

THUMAN = ThumanSynthConfig(people=3, train_poses=2, novel_poses=1, renders_per_mesh=2, raw_items=2, seed=1)


@pytest.fixture(scope="module")
def thuman_set(tmp_path_factory):
    return generate_thuman(tmp_path_factory.mktemp("thuman") / "set", THUMAN, progress=False)


@pytest.fixture(scope="module")
def surreal_set(tmp_path_factory):
    config = SurrealSynthConfig(clips=2, frames=5, seed=2)
    return generate_surreal(tmp_path_factory.mktemp("surreal") / "set", config, progress=False)


def test_thuman_layout_and_counts(thuman_set):
    marker = json.loads((thuman_set / "synthetic.json").read_text())
    n_meshes = THUMAN.people * (THUMAN.train_poses + THUMAN.novel_poses)
    assert marker["n_meshes"] == n_meshes and marker["n_train_meshes"] == THUMAN.people * THUMAN.train_poses
    assert is_thuman_complete(thuman_set, THUMAN) and not is_thuman_complete(thuman_set, ThumanSynthConfig())
    for split, per_mesh in (("train", 2), ("same_view", 1), ("novel_view", 1)):
        assert count_renders(thuman_set / split / "render_128" / "color") == n_meshes * per_mesh
        assert count_renders(thuman_set / f"{split}_view2" / "render_128" / "color") == n_meshes * per_mesh
        assert len(list((thuman_set / split / "render_128" / "bone_params").glob("*.npy"))) == n_meshes
    items = (thuman_set / "raw" / "data_list.txt").read_text().split()
    assert len(items) == THUMAN.raw_items and all((thuman_set / "raw" / item / "mesh.obj").is_file() for item in items)
    assert all(re.fullmatch(r"results_syn_20260101_person\d{3}_1_[FM]/\d{4}", item) for item in items)


def test_thuman_joints_project_onto_the_body(thuman_set):
    """pose_to_camera = cam_from_world pose_to_world, and the torso joints land on the rendered silhouette."""
    inside = []
    for split in ("train", "train_view2", "novel_view"):
        color = thuman_set / split / "render_128" / "color"
        for index in range(4):
            view = read_render(color, index, renders_per_mesh=2 if split.startswith("train") else 1)
            joints = view.pose_to_camera[[0, 3, 6, 9], :3, 3]  # pelvis and spine: always inside the body
            uv = joints @ THUMAN_K.T
            uv = np.round(uv[:, :2] / uv[:, 2:]).astype(int)
            ok = (uv >= 0).all(1) & (uv < 128).all(1)
            inside += [view.mask[v, u] > 0.5 for u, v in uv[ok]]
            # the camera is rigid: pose_to_camera R_j = R_cam pose_to_world R_j for every joint
            cam = view.pose_to_camera[0] @ np.linalg.inv(view.pose_to_world[0])
            assert np.allclose(cam @ view.pose_to_world, view.pose_to_camera, atol=1e-9)  # float64, 2 products
    assert np.mean(inside) > 0.9 and len(inside) > 20


def test_swimwear_share_and_bare_torso(body_model):
    rng = np.random.default_rng(3)
    people = [random_person(rng) for _ in range(400)]
    share = np.mean([p.bare_torso for p in people])
    assert abs(share - SWIMWEAR_SHARE) < 5 * np.sqrt(SWIMWEAR_SHARE * (1 - SWIMWEAR_SHARE) / 400)  # 5 binomial std
    assert not any(random_person(rng, clothed=False).bare_torso for _ in range(20))  # SURREAL-like: no extra draw
    rest = body_model.rest_body(torch.zeros(1, 10)).vertices[0].numpy()
    weights = body_model.smpl.lbs_weights.numpy()
    chest = np.isin(weights.argmax(1), (6, 9))  # spine2 / spine3: under a top unless bare
    swimmer = next(p for p in people if p.bare_torso)
    dressed = next(p for p in people if not p.bare_torso and np.abs(p.top - p.skin).min() > 0.05)
    assert np.array_equal(person_colours(swimmer, rest, weights)[chest], np.tile(swimmer.skin, (chest.sum(), 1)))
    assert not np.isclose(person_colours(dressed, rest, weights)[chest], swimmer.skin).all(1).any()


def test_thuman_raw_item_reproduces_its_scan(thuman_set, body_model):
    item = (thuman_set / "raw" / "data_list.txt").read_text().split()[0]
    folder = thuman_set / "raw" / item
    params = read_smpl_params_txt(folder / "smpl_params.txt")
    assert b"\r\n" in (folder / "smpl_params.txt").read_bytes()  # CRLF, as THUman writes it
    mesh = read_colored_obj(folder / "mesh.obj")
    assert mesh.vertices.shape == (6890, 3) and mesh.faces.shape == (13776, 3) and mesh.colors.std() > 0.05
    zeros = torch.zeros(1, 3)
    body = body_model.pose_zju(torch.as_tensor(params.pose[None]), zeros, zeros, torch.as_tensor(params.betas[None]))
    placed = body.vertices[0].numpy() @ params.world_from_smpl[:3, :3].T + params.world_from_smpl[:3, 3]
    # the text keeps 6 decimals of betas, pose and root (5e-7 each) and the body is float32: ~1e-5 m
    assert np.abs(placed - mesh.vertices).max() < 1e-4


def test_surreal_clips_read_back_and_the_body_lands_on_the_segmentation(surreal_set, body_model):
    clips = json.loads((surreal_set / "synthetic.json").read_text())["clips"]
    assert len(clips) == 2 and all(c.startswith("test/run0/") for c in clips)
    clip = check_clip(surreal_set / clips[0])
    assert clip.n_frames == 5 and np.linalg.det(clip.cam_from_world[:3, :3]) < 0
    segm, depth = read_frame_maps(surreal_set / clips[0], 3)
    assert 500 < (segm > 0).sum() < 0.3 * segm.size and depth[segm == 0].min() == np.float32(1e10)
    assert 6.0 < depth[segm > 0].min() < 10.5  # SURREAL's camera distance
    body = pose_surreal(body_model, clip, [3])
    # the generator posed the body in float32 (joints ~8 m from the origin: ulp ~5e-7, a few dozen operations)
    assert np.allclose(body.world_from_joint[0, :, :3, 3].numpy(), clip.joints3d[3], atol=1e-4)
    labels = np.ones(body_model.n_vertices, np.uint8)
    silhouette = (
        raycast(
            body.vertices[0].double().numpy(),
            body_model.faces,
            np.ones((body_model.n_vertices, 3)),
            labels,
            clip.K,
            clip.cam_from_world,
            320,
            240,
            [],
        )["labels"]
        > 0
    )
    iou = (silhouette & (segm > 0)).sum() / (silhouette | (segm > 0)).sum()
    # the same body through the same camera and sampling: only pixels whose coverage is within float32 rounding of
    # one half can differ (a handful on a ~5000-pixel silhouette)
    assert iou > 0.99, iou


def test_prepare_thuman_renders_raw_items_like_the_stand_in(thuman_set, tmp_path, capsys):
    from pipelines.cli.common import run_cli
    from pipelines.cli.prepare_thuman import main

    out = tmp_path / "prepared"
    assert main([str(thuman_set / "raw"), "--out", str(out), "--renders-per-mesh", "2"]) == 0
    marker = json.loads((out / "thuman.json").read_text())
    assert marker["n_meshes"] == THUMAN.raw_items and marker["n_train_meshes"] == 1
    assert count_renders(out / "train" / "render_128" / "color") == 2 * THUMAN.raw_items
    assert count_renders(out / "novel_view_view2" / "render_128" / "color") == THUMAN.raw_items
    for m in range(THUMAN.raw_items):  # the raw items are meshes 0.. of the stand-in set: the same joint frames
        name = f"bone_params_{m:08d}.npy"
        prepared = np.load(out / "train" / "render_128" / "bone_params" / name)
        original = np.load(thuman_set / "train" / "render_128" / "bone_params" / name)
        # smpl_params.txt keeps 6 decimals of betas and pose (5e-7 each), and the original body was posed in
        # float32: joints ~1 m agree to ~1e-5 m
        assert np.allclose(prepared, original, atol=1e-4)
    view = read_render(out / "same_view" / "render_128" / "color", 0, renders_per_mesh=1)
    assert 0.02 < view.mask.mean() < 0.8 and view.image.max() > 0.2
    bad = tmp_path / "bad" / "results_x_1_F" / "0000"
    bad.mkdir(parents=True)
    (bad / "smpl_params.txt").write_text("ShapeParams\r\n1 2 3\r\n")
    assert run_cli("narf-prepare-thuman", main, [str(tmp_path / "bad"), "--out", str(tmp_path / "never")]) == 2
    assert "smpl_params.txt: line 3 should be 'RootTransformation'" in capsys.readouterr().err
    assert not (tmp_path / "never").exists()
