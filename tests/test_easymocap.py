"""EasyMocap camera files as EasyMocap and Neural Body's custom-data tools write and read them."""

import cv2
import numpy as np
import pytest

from pipelines.datasets.camera import Camera
from pipelines.datasets.easymocap import read_easymocap_cameras, write_easymocap_cameras
from pipelines.datasets.errors import CaptureError


def _mat(key, value):
    value = np.atleast_2d(value)
    data = ", ".join(f"{v:.6f}" for v in value.reshape(-1))
    lines = [f"{key}: !!opencv-matrix", f"  rows: {value.shape[0]}", f"  cols: {value.shape[1]}", "  dt: d"]
    return "\r\n".join([*lines, f"  data: [{data}]", ""])


def _camera(i):
    rvec = np.array([[0.1 * i], [0.2], [-0.3]])
    return np.array([[1000.0 + i, 0, 512], [0, 1001.0, 500], [0, 0, 1]]), rvec, np.array([[0.1], [-0.2 * i], [3.0]])


def _neuralbody_style(folder, n_real=23, n_none=24):
    """The shape of neuralbody's tools/custom/camera_params: 47 names, 24 'none', R_ and Rot_, no dist_ on
    some cameras, CRLF lines and 6 decimals."""
    names = [f"Camera_B{i + 1}" for i in range(n_real)] + ["none"] * n_none
    head = "%YAML:1.0\r\n---\r\nnames:\r\n" + "".join(f'  - "{n}"\r\n' for n in names)
    intri, extri = head, head
    for i in range(n_real):
        K, rvec, tvec = _camera(i)
        intri += _mat(f"K_Camera_B{i + 1}", K)
        if i % 2 == 0:
            intri += _mat(f"dist_Camera_B{i + 1}", np.array([[-0.1, 0.05, 0.001, 0.0, 0.0]]))
        extri += _mat(f"R_Camera_B{i + 1}", rvec) + _mat(f"Rot_Camera_B{i + 1}", cv2.Rodrigues(rvec)[0])
        extri += _mat(f"T_Camera_B{i + 1}", tvec)
    (folder / "intri.yml").write_bytes(intri.encode())
    (folder / "extri.yml").write_bytes(extri.encode())


def test_none_entries_are_skipped_with_one_warning(tmp_path, capsys):
    _neuralbody_style(tmp_path)
    cameras = read_easymocap_cameras(tmp_path)
    assert [c.name for c in cameras] == [f"Camera_B{i + 1}" for i in range(23)]
    assert capsys.readouterr().err.count("skipped 24 of 47") == 1
    for i, cam in enumerate(cameras):
        K, rvec, tvec = _camera(i)
        # the file holds 6 decimals: values agree to half a unit of the 6th decimal
        np.testing.assert_allclose(cam.K, K, atol=5e-7)
        np.testing.assert_allclose(cam.cam_from_world[:3, :3], cv2.Rodrigues(rvec)[0], atol=1e-6)
        np.testing.assert_allclose(cam.cam_from_world[:3, 3], tvec.ravel(), atol=5e-7)
        expected_dist = [-0.1, 0.05, 0.001, 0, 0] if i % 2 == 0 else [0] * 5
        np.testing.assert_allclose(cam.dist, expected_dist, atol=5e-7)
        assert (cam.width, cam.height) == (0, 0)  # no H_/W_ and no images: unknown, never invented


def _rig():
    cams = []
    for i, name in enumerate(["Camera (1)", "Camera [2]", "01"]):
        pose = np.eye(4)
        pose[:3, :3] = cv2.Rodrigues(np.array([0.3, -0.2 * i, 0.1]))[0]
        pose[:3, 3] = [0.1 * i, -0.05, 2.9]
        K = np.array([[812.5, 0, 255.5], [0, 811.25, 256.25], [0, 0, 1]])
        cams.append(Camera(name, K, np.array([-0.2, 0.05, 1e-3, -2e-4, 0.01]), pose, 512 if i else 0, 384))
    return cams


def test_names_with_spaces_and_brackets_round_trip_exactly(tmp_path):
    cams = _rig()
    write_easymocap_cameras(tmp_path, cams)
    text = (tmp_path / "intri.yml").read_bytes()
    assert text.startswith(b"%YAML:1.0\r\n---\r\n") and b'  - "Camera (1)"\r\n' in text
    assert b"H_Camera (1)" not in text and b"W_Camera [2]: 512" in text  # never an unknown size written as 0
    back = read_easymocap_cameras(tmp_path)
    assert [c.name for c in back] == [c.name for c in cams]
    for a, b in zip(cams, back):
        # the values are written with their shortest exact text; only R goes through Rodrigues twice
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.dist, b.dist)
        np.testing.assert_array_equal(a.cam_from_world[:3, 3], b.cam_from_world[:3, 3])
        np.testing.assert_allclose(a.cam_from_world[:3, :3], b.cam_from_world[:3, :3], atol=1e-12)
        assert (b.width, b.height) == ((a.width, a.height) if a.width else (0, 0))
    storage = cv2.FileStorage(str(tmp_path / "extri.yml"), cv2.FILE_STORAGE_READ)
    rot = storage.getNode("Rot_Camera [2]").mat()
    np.testing.assert_array_equal(rot, cams[1].cam_from_world[:3, :3])


def test_image_sizes_are_checked_or_filled(tmp_path):
    cams = _rig()
    write_easymocap_cameras(tmp_path / "cams", cams)
    for name, (w, h) in {"Camera (1)": (640, 480), "Camera [2]": (512, 384)}.items():
        (tmp_path / "images" / name).mkdir(parents=True)
        cv2.imwrite(str(tmp_path / "images" / name / "000000.jpg"), np.zeros((h, w, 3), np.uint8))
    back = read_easymocap_cameras(tmp_path / "cams", images=tmp_path / "images")
    assert [(c.width, c.height) for c in back] == [(640, 480), (512, 384), (512, 384)]
    cv2.imwrite(str(tmp_path / "images" / "Camera [2]" / "000000.jpg"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(CaptureError, match=r"Camera \[2\]' is 512x384 .* are 10x10"):
        read_easymocap_cameras(tmp_path / "cams", images=tmp_path / "images")


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: s.replace("data: [1000.000000", "data: [.nan"), "K is malformed"),
        (lambda s: s.replace("data: [1000.000000, 0.000000, 512.000000", "data: [0.0, 0.0, 0.0"), "singular K"),
    ],
)
def test_bad_matrices_name_the_camera(tmp_path, edit, message):
    _neuralbody_style(tmp_path, n_real=2, n_none=0)
    (tmp_path / "intri.yml").write_text(edit((tmp_path / "intri.yml").read_text()))
    with pytest.raises(CaptureError, match=f"Camera_B1.*{message}|{message}"):
        read_easymocap_cameras(tmp_path)


def test_unwritable_names_are_refused(tmp_path):
    cam = _rig()[0]
    for bad in ('say "cheese"', "a:b", "none", " padded"):
        with pytest.raises(ValueError, match="cannot be written"):
            write_easymocap_cameras(tmp_path, [Camera(bad, cam.K, cam.dist, cam.cam_from_world, 1, 1)])
    assert not (tmp_path / "intri.yml").exists()


@pytest.mark.parametrize(
    "intri, message",
    [
        # OpenCV 5 raises SystemError (not cv2.error) on this one
        ('%YAML:1.0\n---\nnames: [ "a" \n  K_a: {{{ \n', "intri.yml: not an OpenCV YAML file"),
        (
            '%YAML:1.0\n---\nnames: [ "a" ]\nK_a: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [ 1, 2 ]\n',
            "camera 'a' cannot be read from intri.yml / extri.yml",
        ),
    ],
)
def test_files_opencv_cannot_parse_are_one_line(tmp_path, intri, message):
    (tmp_path / "intri.yml").write_text(intri)
    (tmp_path / "extri.yml").write_text('%YAML:1.0\n---\nnames: [ "a" ]\n')
    with pytest.raises(CaptureError, match=message) as caught:
        read_easymocap_cameras(tmp_path)
    assert "\n" not in str(caught.value)


def test_a_file_of_skipped_cameras_only_is_one_error_line(tmp_path, capsys):
    """Every name 'none': the error alone, no note before it (one line, our own)."""
    from pipelines.datasets.errors import CaptureError

    (tmp_path / "intri.yml").write_text('%YAML:1.0\n---\nnames:\n  - "none"\n  - "none"\n')
    (tmp_path / "extri.yml").write_text('%YAML:1.0\n---\nnames:\n  - "none"\n  - "none"\n')
    capsys.readouterr()
    with pytest.raises(CaptureError, match=r"no camera with K .*all 2 camera names are 'none'"):
        read_easymocap_cameras(tmp_path)
    assert capsys.readouterr().err == ""
