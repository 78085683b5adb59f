"""THUman raw items and render_128 views: the readers against files written as DeepHuman and NARF write them."""

import cv2
import numpy as np
import pytest

from pipelines.datasets.errors import CaptureError
from pipelines.datasets.thuman import (
    THUMAN_K,
    count_renders,
    item_gender,
    read_cam_txt,
    read_colored_obj,
    read_render,
    read_smpl_params_txt,
)


def _smpl_params_text(betas, root, pose, newline="\r\n"):
    lines = ["ShapeParams", " ".join(f"{b:.6f}" for b in betas) + " ", "RootTransformation"]
    lines += [" ".join(f"{v:.6f}" for v in row) + " " for row in root]
    lines += ["JointRotations"] + [f"{v:.6f}" for v in pose]
    return newline.join(lines) + newline


def test_smpl_params_txt_crlf_and_lf(tmp_path):
    rng = np.random.default_rng(0)
    betas, pose = rng.normal(size=10), rng.normal(0, 0.3, 72)
    root = np.eye(4)
    root[:3, :3] = cv2.Rodrigues(np.array([0.1, 0.2, -0.3]))[0]
    root[:3, 3] = [0.1, -0.2, 1.5]
    for newline in ("\r\n", "\n"):
        path = tmp_path / "smpl_params.txt"
        path.write_bytes(_smpl_params_text(betas, root, pose, newline).encode())
        params = read_smpl_params_txt(path)
        # written with 6 decimals: the round trip is exact to half a unit of the 6th decimal
        assert np.allclose(params.betas, betas, atol=5e-7) and np.allclose(params.pose, pose, atol=5e-7)
        assert np.allclose(params.world_from_smpl, root, atol=5e-7)


def test_smpl_params_txt_errors_name_the_line(tmp_path):
    good = _smpl_params_text(np.zeros(10), np.eye(4), np.zeros(72))
    path = tmp_path / "smpl_params.txt"
    path.write_text(good.replace("JointRotations", "Joints"))
    with pytest.raises(CaptureError, match="line 8 should be 'JointRotations', found 'Joints'"):
        read_smpl_params_txt(path)
    path.write_text(good.replace("0.000000 0.000000 0.000000 0.000000 0.000000 ", "0.0 x ", 1))
    with pytest.raises(CaptureError, match="line 2 is not a list of numbers"):
        read_smpl_params_txt(path)
    path.write_text(good.rsplit("\r\n", 3)[0] + "\r\n")
    with pytest.raises(CaptureError, match="70 joint rotation values after 'JointRotations', expected 72"):
        read_smpl_params_txt(path)


def test_colored_obj_and_cam_txt(tmp_path):
    obj = tmp_path / "mesh.obj"
    obj.write_text("# scan\nv 0 0 0 1 0 0\nv 1 0 0 0 1 0\nv 0 1 0\nv 0 0 1 0 0 1\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\n")
    mesh = read_colored_obj(obj)
    assert mesh.vertices.shape == (4, 3) and mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3]]  # the quad is fanned
    assert mesh.colors[2].tolist() == [0.5, 0.5, 0.5] and mesh.colors[0].tolist() == [1.0, 0.0, 0.0]
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(CaptureError, match="mesh.obj: the mesh has no vertex colours"):
        read_colored_obj(obj)
    obj.write_text("v 0 0 0 1 1 1\nf 1 2 3\n")
    with pytest.raises(CaptureError, match="a face refers to a vertex outside 1..1"):
        read_colored_obj(obj)
    cam = tmp_path / "cam.txt"
    cam.write_text("1 0 0 0\r\n0 1 0 0\r\n0 0 1 2\r\n0 0 0 1\r\n")
    assert read_cam_txt(cam)[2, 3] == 2.0
    assert item_gender(tmp_path / "results_gyx_20181017_lst_1_F" / "0001") == "female"
    with pytest.raises(CaptureError, match="not inside a THUman item folder"):
        item_gender(tmp_path / "somewhere")


def test_render_128_reads_bgra_and_transforms(tmp_path):
    color = tmp_path / "render_128" / "color"
    color.mkdir(parents=True)
    rgba = np.zeros((128, 128, 4), np.uint8)
    rgba[40:90, 50:80] = (200, 100, 50, 255)  # an RGBA body on a transparent black background
    for index in range(3):
        cv2.imwrite(str(color / f"color_{index:08d}.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
        transforms = np.tile(np.eye(4), (24, 1, 1))
        transforms[:, 2, 3] = index
        np.save(color / f"pose_to_camera_{index:08d}.npy", transforms)
        np.save(color / f"pose_to_world_{index:08d}.npy", transforms)
    assert count_renders(color) == 3
    view = read_render(color, 2, renders_per_mesh=2)
    assert (view.mesh, view.view) == (1, 0) and view.pose_to_camera[0, 2, 3] == 2
    # the red channel comes back as red (BGRA on disk), exact multiples of 1/255
    # uint8 / 255 in float32 against float64: rounding ~3e-8, inside allclose's defaults
    assert np.allclose(view.image[60, 60], np.array([200, 100, 50]) / 255) and view.image[0, 0].max() == 0
    assert view.mask[60, 60] == 1 and view.mask[0, 0] == 0 and np.array_equal(view.K, THUMAN_K)
    cv2.imwrite(str(color / "color_00000001.png"), np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(CaptureError, match="color_00000001.png: shape \\(64, 64, 3\\), expected a 128x128 BGRA"):
        read_render(color, 1, renders_per_mesh=2)
    (color / "pose_to_world_00000000.npy").unlink()
    with pytest.raises(CaptureError, match="pose_to_world_00000000.npy: missing"):
        read_render(color, 0, renders_per_mesh=2)
