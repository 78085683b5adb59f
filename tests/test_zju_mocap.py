import shutil

import cv2
import numpy as np
import pytest

from pipelines.datasets.camera import Camera, resized_mask
from pipelines.datasets.capture import ZjuCapture, make_protocol
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.zju_mocap import param_index_from_image, read_annots, write_annots


@pytest.fixture
def capture_copy(tiny_capture, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(tiny_capture, dst, ignore=shutil.ignore_patterns("calib"))
    return dst


def test_load_frame_follows_neuralbody_order(tiny_capture):
    cap = ZjuCapture(tiny_capture, ratio=0.5)
    frame = cap.load_frame(2, 1)
    assert frame.image.shape == (128, 128, 3) and frame.image.dtype == np.float32
    assert set(np.unique(frame.mask)) <= {0.0, 1.0} and frame.mask.sum() > 100
    outside = (frame.mask == 0) & ~frame.band
    assert np.all(frame.image[outside] == 0.0)  # black background
    assert frame.band.any() and not frame.band[frame.mask.astype(bool) & ~frame.band].any()
    raw_cameras, _ = read_annots(tiny_capture / "annots.npy")
    # halving and adding 0.5 are exact in binary: allclose's defaults; the principal point as cv2.resize's pixel
    # centres put it, (c + 0.5) / 2 - 0.5 (docs/formats.md §0), not c / 2
    expected_K = raw_cameras[1].K.copy()
    expected_K[:2, :2] *= 0.5
    expected_K[:2, 2] = (expected_K[:2, 2] + 0.5) * 0.5 - 0.5
    assert np.allclose(frame.camera.K, expected_K) and np.all(frame.camera.dist == 0)
    assert 2.5 < np.linalg.norm(frame.camera.centre[:2]) < 3.5  # T converted from millimetres
    white = ZjuCapture(tiny_capture, ratio=0.5, white_background=True).load_frame(2, 1)
    assert np.all(white.image[outside] == 1.0)
    undistorted = cv2.undistort(
        cv2.cvtColor(cv2.imread(str(frame.image_path)), cv2.COLOR_BGR2RGB).astype(np.float32) / 255,
        raw_cameras[1].K,
        raw_cameras[1].dist,
    )
    expected = cv2.resize(undistorted, (128, 128), interpolation=cv2.INTER_AREA)
    inside = frame.mask.astype(bool)
    # the same OpenCV float32 operations in the same order: identical up to SIMD lane order (a few eps32 ~ 5e-7)
    assert np.abs(expected[inside] - frame.image[inside]).max() < 1e-6


def test_mask_sources(tiny_capture):
    cihp = ZjuCapture(tiny_capture, ratio=1.0).load_frame(0, 0)
    binary = ZjuCapture(tiny_capture, ratio=1.0, mask_source="mask").load_frame(0, 0)
    union = ZjuCapture(tiny_capture, ratio=1.0, mask_source="union").load_frame(0, 0)
    assert np.array_equal(cihp.mask, binary.mask) and np.array_equal(union.mask, cihp.mask)
    assert cihp.labels.max() >= 13


def test_313_layout(tiny_capture_313):
    cap = ZjuCapture(tiny_capture_313, ratio=1.0)
    assert cap.ims[0][1] == "Camera (2)/CoreView_313_Camera_(2)_0001_2019-08-23_16-08-50.592.jpg"
    frame = cap.load_frame(2, 1)
    assert frame.frame_index == 2
    assert (tiny_capture_313 / "params" / "3.npy").is_file() and not (tiny_capture_313 / "params" / "0.npy").exists()
    # the reader casts float64 params to float32: allclose's rtol 1e-5 covers that rounding (6e-8 relative)
    assert np.allclose(
        cap.params(2).poses, np.load(tiny_capture_313 / "params" / "3.npy", allow_pickle=True).item()["poses"][0]
    )
    assert cap.vertices(2).shape == (6890, 3)


def test_param_index_from_image():
    assert param_index_from_image("Camera_B1/000012.jpg") == (12, 12)
    assert param_index_from_image("Camera (3)/CoreView_315_Camera_(3)_0013_2019-08-23_16-08-50.592.jpg") == (12, 13)
    with pytest.raises(CaptureError, match="cannot read a frame index"):
        param_index_from_image("Camera_B1/image.jpg")


def test_protocols():
    narf = make_protocol("narf", 240, 21)
    assert narf.train_views == (0, 6, 12, 18) and len(narf.test_views) == 17
    assert narf.train_frames == tuple(range(216)) and narf.novel_frames == tuple(range(216, 240))
    assert narf.interval == 4  # 24 novel frames: every 4th keeps 6 evaluation frames
    assert narf.split("novel_pose") == [(f, c) for f in range(216, 240, 4) for c in narf.test_views]
    assert narf.split("same_pose_novel_view")[:2] == [(0, 1), (0, 2)]
    assert len(narf.split("novel_pose_same_view")) == 6 * 4
    nb = make_protocol("neuralbody", 2185, 21, subject_id=315)
    assert nb.train_frames == tuple(range(400)) and nb.novel_frames == tuple(range(400, 1400)) and nb.interval == 30
    kick = make_protocol("neuralbody", 1171, 23, subject_id=390)
    assert kick.train_frames[0] == 700 and kick.novel_frames == tuple(range(0, 700))
    with pytest.raises(ValueError, match="unknown split"):
        narf.split("everything")


class TestBadInput:
    def test_missing_camera_folder(self, capture_copy):
        shutil.rmtree(capture_copy / "Camera_B3")
        with pytest.raises(CaptureError, match=r"Camera_B3: camera folder listed in annots.npy is missing"):
            ZjuCapture(capture_copy)

    def test_unreadable_image(self, capture_copy):
        (capture_copy / "Camera_B2" / "000001.jpg").write_bytes(b"garbage")
        with pytest.raises(CaptureError, match=r"000001.jpg: missing or unreadable image"):
            ZjuCapture(capture_copy).load_frame(1, 1)

    def test_mask_size_mismatch(self, capture_copy):
        path = capture_copy / "mask_cihp" / "Camera_B1" / "000000.png"
        cv2.imwrite(str(path), np.zeros((100, 80), np.uint8))
        with pytest.raises(CaptureError, match=r"000000.png: mask is 80x100 but the image is 256x256"):
            ZjuCapture(capture_copy).load_frame(0, 0)

    def test_params_wrong_shape_or_nan(self, capture_copy):
        path = capture_copy / "new_params" / "1.npy"
        data = np.load(path, allow_pickle=True).item()
        np.save(path, dict(data, poses=np.zeros((1, 69))))
        with pytest.raises(CaptureError, match=r"1.npy: 'poses' has shape \(1, 69\)"):
            ZjuCapture(capture_copy).params(1)
        np.save(path, dict(data, Th=np.array([[0.0, np.nan, 0.0]])))
        with pytest.raises(CaptureError, match=r"1.npy: 'Th' contains NaN"):
            ZjuCapture(capture_copy).params(1)
        (capture_copy / "new_params" / "2.npy").unlink()
        with pytest.raises(CaptureError, match=r"2.npy: missing"):
            ZjuCapture(capture_copy).params(2)

    def test_frame_count_mismatch(self, capture_copy):
        cameras, ims = read_annots(capture_copy / "annots.npy")
        annots = np.load(capture_copy / "annots.npy", allow_pickle=True).item()
        annots["ims"][2]["ims"] = annots["ims"][2]["ims"][:3]
        np.save(capture_copy / "annots.npy", annots)
        with pytest.raises(CaptureError, match=r"annots.npy: ims\[2\] lists 3 images but cams has 4 cameras"):
            ZjuCapture(capture_copy)
        with pytest.raises(ValueError, match="each ims entry"):
            write_annots(capture_copy / "x.npy", cameras, [ims[0][:2]])

    def test_not_a_subject_folder(self, tmp_path):
        with pytest.raises(CaptureError, match="no annots.npy"):
            ZjuCapture(tmp_path)

    def test_out_of_range(self, tiny_capture):
        with pytest.raises(CaptureError, match="frame 9 out of range"):
            ZjuCapture(tiny_capture).load_frame(9, 0)


def test_pixels_of_unknown_owner_leave_the_mask_for_the_band(capture_copy):
    """A prepared capture's ``mask_unknown/`` (somebody in front of the person): those pixels are neither the
    person's nor background: out of the mask and its CIHP labels, in the band (which the losses and the evaluation's
    person pixels skip), in the background's colour; a view without the file has no such pixels."""
    cap = ZjuCapture(capture_copy, ratio=1.0)
    before = cap.load_frame(0, 0)
    raw = cv2.imread(str(capture_copy / "mask_cihp" / cap.ims[0][0].replace(".jpg", ".png")), 0) > 0
    unknown = np.zeros_like(raw)
    rows = np.nonzero(raw.any(1))[0]
    unknown[rows.min() : (rows.min() + rows.max()) // 2] = True  # the upper half of the person and the background
    path = capture_copy / "mask_unknown" / cap.ims[0][0].replace(".jpg", ".png")
    path.parent.mkdir(parents=True)
    cv2.imwrite(str(path), unknown.astype(np.uint8))
    after = ZjuCapture(capture_copy, ratio=1.0).load_frame(0, 0)
    assert before.unknown is None and after.unknown is not None and after.unknown.any()
    assert not after.mask[after.unknown].any() and after.band[after.unknown].all()
    assert not after.labels[after.unknown].any() and after.mask[~after.unknown].sum() > 100
    # the person's pixels with a known owner are those of before (undistortion moves both masks alike)
    assert np.array_equal(after.mask.astype(bool), before.mask.astype(bool) & ~after.unknown)
    # somebody else's colours are not kept: the background's, where the person was before
    was_person = after.unknown & (before.mask > 0)
    assert before.image[was_person].any() and not after.image[after.unknown].any()
    assert ZjuCapture(capture_copy, ratio=1.0).load_frame(0, 1).unknown is None


def test_an_unknown_mask_of_the_wrong_size_is_refused_naming_the_file(capture_copy):
    cap = ZjuCapture(capture_copy, ratio=1.0)
    path = capture_copy / "mask_unknown" / cap.ims[0][0].replace(".jpg", ".png")
    path.parent.mkdir(parents=True)
    cv2.imwrite(str(path), np.ones((7, 9), np.uint8))
    with pytest.raises(CaptureError, match=r"mask_unknown.*: mask is 9x7 but the image is"):
        cap.load_frame(0, 0)


@pytest.mark.parametrize("ratio", [0.5, 0.3])
def test_a_resized_camera_sees_a_point_where_cv2_resize_puts_it(ratio):
    """A small bright blob drawn around a point's projection, resized by area as the readers resize images, has its
    centroid where the resized camera projects the point (whole and fractional ratios)."""
    K = np.array([[300.0, 0, 99.3], [0, 310, 61.7], [0, 0, 1]])
    camera = Camera("c", K, np.zeros(5), np.eye(4), 200, 120)
    point = np.array([0.07, -0.04, 1.0])
    u, v = (K @ point)[:2]
    rows, cols = np.mgrid[0:120, 0:200]
    blob = np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / (2 * 3.0**2)).astype(np.float32)
    small = camera.scaled(ratio)
    resized = cv2.resize(blob, (small.width, small.height), interpolation=cv2.INTER_AREA).astype(np.float64)
    r, c = np.mgrid[0 : small.height, 0 : small.width]
    centroid = np.array([(resized * c).sum(), (resized * r).sum()]) / resized.sum()
    projected = (small.K @ point)[:2]
    # the blob (sigma 3 px, 10 sigma from every edge) keeps its centroid through area resampling up to float32
    # rounding of ~1e4 summed pixels (~1e-3 px); the convention that scales the principal point with the focal
    # length is off by (1 / ratio - 1) / 2 old pixels, 0.25-0.35 new ones
    assert np.abs(centroid - projected).max() < 0.01


def test_a_resized_mask_keeps_its_place_and_its_size():
    """A disc resized by half by area (``resized_mask``) is centred where ``Camera.scaled`` puts its centre and keeps
    its area; an edge through the middle of every pixel keeps half of those pixels, alternately."""
    rows, cols = np.mgrid[0:200, 0:240]
    centre = np.array([117.3, 93.6])  # (u, v) in the original
    disc = (cols - centre[0]) ** 2 + (rows - centre[1]) ** 2 < 40.0**2
    small = resized_mask(disc, (120, 100))
    r, c = np.nonzero(small)
    camera = Camera(
        "c", np.array([[100.0, 0, centre[0]], [0, 100, centre[1]], [0, 0, 1]]), np.zeros(5), np.eye(4), 240, 200
    )
    expected = camera.scaled(0.5).K[:2, 2]  # where the point on the optical axis, the disc's centre, lands
    # a disc of ~5,000 pixels at half size: the edge pixels' rounding moves its centroid by ~0.01 px and its area
    # by a fraction of its ~250-pixel outline; the nearest pixel's value moves the centroid 0.25 px up and left
    assert np.abs(np.array([c.mean(), r.mean()]) - expected).max() < 0.05
    assert abs(small.sum() - disc.sum() / 4) < 0.02 * disc.sum() / 4
    edge = np.zeros((8, 8), bool)
    edge[:, :3] = True  # the edge runs through the middle of the second column of the half-size image
    halved = resized_mask(edge, (4, 4))
    assert halved[:, 0].all() and not halved[:, 2:].any() and halved[:, 1].sum() == 2
