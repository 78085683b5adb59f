"""narf-prepare-capture on the synthetic capture written back as a raw recording (videos, a Qualisys file of the
true cameras, OpenPose JSON projected from the true joints with 1 px of noise, the true masks): the prepared
capture's cameras, joints and body must match the truth; a camera turned by 5 degrees is flagged; bad input is one
line and exit 2 with nothing written. The readers are checked against hand-computed conversions."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from bad_input import prepare_error
from scipy.spatial.transform import Rotation

from pipelines.body.model import BodyModel
from pipelines.body.motion import stage_of
from pipelines.cli import prepare_capture
from pipelines.cli.common import run_cli
from pipelines.datasets.camera import project_distorted
from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.keypoints import TARGET_JOINTS, read_openpose, to_targets, write_openpose
from pipelines.datasets.rig_files import read_qualisys, read_rig, read_toml, write_qualisys
from pipelines.prepare.people.multiview import project, triangulate, triangulate_robust
from pipelines.synthetic.recording import true_joints, write_recording

NOISE_PX = 1.0  # the keypoint noise of the recording fixture (tests/conftest.py)


def _prepare(rec: Path, out: Path, *extra) -> int:
    argv = [str(rec), "--out", str(out), "--keypoints", str(rec / "keypoints"), "--masks", str(rec / "masks")]
    return run_cli("narf-prepare-capture", prepare_capture.main, [*argv, "--quiet", *extra])


@pytest.fixture(scope="module")
def prepared(recording):
    assert _prepare(recording / "rec", recording / "out") == 0
    return recording / "out"


def test_prepared_capture_matches_the_truth(recording, prepared):
    truth, out = ZjuCapture(recording / "truth"), ZjuCapture(prepared)
    for true_cam, cam in zip(truth.cameras, out.cameras):
        # intrinsics pass through (qca text of repr floats); the calibration as given round-trips to 1e-9 m with
        # --keep-calibration (tests/test_silhouettes.py)
        assert cam.name == true_cam.name and (cam.width, cam.height) == (true_cam.width, true_cam.height)
        np.testing.assert_allclose(cam.K, true_cam.K, rtol=1e-12)
        np.testing.assert_allclose(cam.dist, true_cam.dist, atol=1e-12)
        # the silhouette stage may move an exact camera only as far as 1 px of keypoint noise on a 256-px image
        # supports (~0.2 degrees, ~1 cm at 3 m); its prior's scale is 1 degree and 1 cm
        turn = np.linalg.norm(cv2.Rodrigues(cam.cam_from_world[:3, :3] @ true_cam.cam_from_world[:3, :3].T)[0])
        assert np.degrees(turn) < 0.2 and np.linalg.norm(cam.centre - true_cam.centre) < 0.01
    joints = true_joints(truth, BodyModel())[:, list(TARGET_JOINTS)]
    error_cm = 100 * np.linalg.norm(np.load(prepared / "keypoints3d.npy") - joints, axis=-1)
    # 1 px of noise is about 1 cm at these cameras (f ~ 280 px at ~3 m): the median stays near it, no joint is far
    assert np.median(error_cm) < 2.0 and error_cm.max() < 6.0, error_cm
    vertices = np.stack([truth.vertices(f) for f in range(truth.n_frames)])
    fitted = np.stack([out.vertices(f) for f in range(out.n_frames)])
    # joints leave limb twist and girth to the priors: a few cm on the surface, never a wrong limb
    distance_cm = 100 * np.linalg.norm(vertices - fitted, axis=-1)
    assert np.median(distance_cm) < 3.0 and np.percentile(distance_cm, 95) < 10.0
    report = json.loads((prepared / "report.json").read_text())
    assert report["frames"]["kept"] == 10 and not report["flagged_cameras"]
    for name, camera in report["cameras"].items():
        assert (camera["recording"], camera["matched_by"]) == (f"{name}.mp4", "name")
        # median 2D error of 1-px Gaussian noise is 1.18 px; the fit adds little
        assert camera["body_reprojection_px"] < 2.5 and camera["iou_mean"] > 0.75
    splits = json.loads((prepared / "splits.json").read_text())
    assert splits["novel_frames"] == [7, 8, 9] and splits["test_views"] == [3] and splits["train_views"] == [0, 1, 2]
    protocol = out.protocol("neuralbody")
    assert protocol.split("novel_pose") == [(f, 3) for f in (7, 8, 9)]
    frame = out.load_frame(0, 0)
    assert frame.image.shape == (128, 128, 3) and frame.mask.sum() > 100
    assert (prepared / "overlay" / "overlay.mp4").is_file() and len(
        list((prepared / "overlay" / "Camera_B1").glob("*.jpg"))
    ) == 10


def test_a_turned_camera_is_flagged(recording, tmp_path):
    rec = tmp_path / "rec"
    shutil.copytree(recording / "rec", rec)
    cameras = read_qualisys(rec / "calibration" / "Calib.qca.txt")
    turn = cv2.Rodrigues(np.array([0.0, np.deg2rad(5.0), 0.0]))[0]
    pose = cameras[1].cam_from_world.copy()
    pose[:3, :3] = turn @ pose[:3, :3]  # turned about its own centre (which stays where it is)
    pose[:3, 3] = -pose[:3, :3] @ cameras[1].centre
    cameras[1] = type(cameras[1])(**{**cameras[1].__dict__, "cam_from_world": pose})
    write_qualisys(rec / "calibration" / "Calib.qca.txt", cameras)
    # a short silhouette stage: its camera correction (a prior of 1 degree) cannot undo 5 degrees at any length
    assert _prepare(rec, tmp_path / "out", "--silhouette-iterations", "100") == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert list(report["flagged_cameras"]) == ["Camera_B2"], report["flagged_cameras"]


def test_qualisys_conversion_by_hand(tmp_path):
    text = (
        '<calibration><cameras><camera model="none" serial="cam2"><fov_video left="8" top="0" right="1087" '
        'bottom="1919"/><transform r11="1" r12="0" r13="0" r21="0" r22="0" r23="1" r31="0" r32="-1" r33="0" x="1000" '
        'y="-2000" z="1500"/><intrinsic focalLengthU="64000" focalLengthV="64064" centerPointU="35200" '
        'centerPointV="61440" radialDistortion1="-0.05" radialDistortion2="0.1" tangentalDistortion1="0.001" '
        'tangentalDistortion2="0" radialDistortion3="0"/></camera><camera model="Oqus" serial="marker"/></cameras>'
        "</calibration>"
    )
    (tmp_path / "c.qca.txt").write_text(text)
    (camera,) = read_rig(tmp_path / "c.qca.txt")  # the marker-only camera is skipped, as Pose2Sim does
    # fx = 64000/64, cx = 35200/64 - left 8; distortion as written; R = diag(1,-1,-1) . rows r11..r33; t = -R . C
    np.testing.assert_allclose(camera.K, [[1000, 0, 542], [0, 1001, 960], [0, 0, 1]])
    np.testing.assert_allclose(camera.dist, [-0.05, 0.1, 0.001, 0, 0])
    rotation = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    np.testing.assert_allclose(camera.cam_from_world[:3, :3], rotation)
    np.testing.assert_allclose(camera.cam_from_world[:3, 3], -rotation @ [1.0, -2.0, 1.5])
    assert (camera.width, camera.height) == (1080, 1920)


def test_toml_reader_by_hand(tmp_path):
    (tmp_path / "calib.toml").write_text(
        '[cam_01]\nname = "cam01"\nsize = [ 640.0, 480.0]\nmatrix = [ [ 500.0, 0.0, 320.0], [ 0.0, 500.0, 240.0], '
        "[ 0.0, 0.0, 1.0]]\ndistortions = [ -0.1, 0.01, 0.0, 0.0]\nrotation = [ 0.0, 0.0, 1.5707963267948966]\n"
        "translation = [ 0.1, 0.2, 3.0]\nfisheye = false\n\n[metadata]\nadjusted = false\nerror = 0.0\n"
    )
    (camera,) = read_toml(tmp_path / "calib.toml")
    np.testing.assert_allclose(camera.cam_from_world[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(camera.cam_from_world[:3, 3], [0.1, 0.2, 3.0])
    assert camera.name == "cam01" and (camera.width, camera.height) == (640, 480) and camera.dist[0] == -0.1
    singular = (tmp_path / "calib.toml").read_text().replace("[ 500.0, 0.0, 320.0]", "[ 0.0, 0.0, 320.0]")
    (tmp_path / "singular.toml").write_text(singular)
    with pytest.raises(CaptureError, match="singular.toml: camera 'cam01' has no usable intrinsics"):
        read_rig(tmp_path / "singular.toml")


def test_triangulation_against_opencv():
    rng = np.random.default_rng(1)
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    # three cameras 4 m from the origin, 60 degrees apart around the y axis, looking at it
    poses = [cv2.Rodrigues(np.array([0.0, angle, 0.0]))[0] for angle in np.deg2rad([-60.0, 0.0, 60.0])]
    P = np.stack([K @ np.hstack([R, np.array([[0.0], [0.0], [4.0]])]) for R in poses])
    points = rng.normal(0, 0.5, (20, 3))
    xy = project(P, points)  # (20, 3, 2)
    reference = cv2.triangulatePoints(P[0], P[1], xy[:, 0].T, xy[:, 1].T)
    two_views = triangulate(P, xy, np.array([1.0, 1.0, 0.0])[None].repeat(20, 0))
    # noise-free projections: both solve the same null space in float64
    np.testing.assert_allclose(two_views, (reference[:3] / reference[3]).T, atol=1e-9)
    xy[:5, 2] += 40.0  # a wrong view for five points: dropped, the two others agree exactly
    robust, weights = triangulate_robust(P, xy, np.ones((20, 3)), np.full(3, 480.0), threshold=0.01)
    np.testing.assert_allclose(robust, points, atol=1e-9)
    assert (weights[:5, 2] == 0).all() and (weights[5:] > 0).all()


def test_keypoint_layouts_map_to_the_same_targets():
    body25 = np.zeros((25, 3))
    body25[17], body25[18] = (10, 20, 0.9), (30, 40, 0.8)  # ears -> head = their midpoint, least confidence
    head = to_targets(body25, "body25")[list(TARGET_JOINTS).index(15)]
    np.testing.assert_allclose(head, [20, 30, 0.8])


def test_every_layout_gives_the_same_targets_and_25_points_are_told_apart(recording):
    """Keypoints of each layout placed on the true joints (as ``write_recording`` does) read back as the same targets,
    wherever the layout has them; the 25-point check tells BODY_25 from BODY_25B on every camera of the synthetic
    recording, and says nothing when the points it needs are not seen."""
    from pipelines.datasets.keypoints import TARGETS, keypoints_from_joints, layout_of_25

    truth = ZjuCapture(recording / "truth")
    joints = true_joints(truth, BodyModel())
    for camera in truth.cameras:
        pixels = [project_distorted(camera, j) for j in joints]
        reference = to_targets(np.stack([keypoints_from_joints(p, "body25") for p in pixels]), "body25")
        for layout in ("body25b", "halpe26", "coco17", "coco18"):
            got = to_targets(np.stack([keypoints_from_joints(p, layout) for p in pixels]), layout)
            has = [t for t, target in enumerate(TARGETS) if layout in target.sources]
            np.testing.assert_array_equal(got[:, has], reference[:, has])
            assert (got[:, [t for t in range(len(TARGETS)) if t not in has], 2] == 0).all()
        for layout in ("body25", "body25b"):
            assert layout_of_25([keypoints_from_joints(p, layout) for p in pixels]) == layout, (camera.name, layout)
    legs_only = np.zeros((10, 25, 3))
    legs_only[:, 9:15] = (100.0, 200.0, 0.9)
    assert layout_of_25(list(legs_only)) is None


def test_body25b_files_prepare_the_truth_and_are_never_read_as_body25(recording, tmp_path, capsys):
    """Pose2Sim's BODY_25B files (its names: ``cam.0003.json`` in ``cam_json/``) prepare the same capture as BODY_25
    ones; forced to BODY_25, or left undecidable, they are refused in one line."""
    rec = write_recording(recording / "truth", tmp_path / "rec", noise_px=NOISE_PX, layout="body25b")
    for path in sorted((rec / "keypoints").rglob("*_keypoints.json")):
        frame = int(path.name.split("_")[-2])
        path.rename(path.with_name(f"{path.parent.name[:-5]}.{frame:04d}.json"))
    flags = ["--keypoints", rec / "keypoints", "--masks", rec / "masks", "--quiet", "--silhouette-iterations", "0"]
    assert "--keypoint-layout body25b" in prepare_error(
        capsys, [rec, "--out", tmp_path / "x", *flags, "--keypoint-layout", "body25"]
    )
    assert (
        run_cli(
            "narf-prepare-capture", prepare_capture.main, [str(a) for a in [rec, "--out", tmp_path / "out", *flags]]
        )
        == 0
    )
    assert "give --keypoints too" in prepare_error(
        capsys, [rec, "--out", tmp_path / "z", "--keypoint-layout", "body25"]
    )
    truth = ZjuCapture(recording / "truth")
    joints = true_joints(truth, BodyModel())[:, list(TARGET_JOINTS)]
    error_cm = 100 * np.linalg.norm(np.load(tmp_path / "out" / "keypoints3d.npy") - joints, axis=-1)
    # the same bound as BODY_25's (test_prepared_capture_matches_the_truth): BODY_25B has no pelvis point
    assert np.nanmedian(error_cm) < 2.0 and np.nanmax(error_cm) < 6.0, error_cm
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert all("keypoints read as OpenPose BODY_25B" in c["notes"] for c in report["cameras"].values())
    for path in (rec / "keypoints").rglob("*.json"):
        people = [p.copy() for p in read_openpose(path)]
        for p in people:
            p[:9, 2] = 0  # face and arms unseen: neither test can run
        write_openpose(path, people)
    assert "cannot tell BODY_25 from BODY_25B" in prepare_error(capsys, [rec, "--out", tmp_path / "y", *flags])


def test_training_views_of_different_sizes_sample_only_their_own_pixels():
    from types import SimpleNamespace

    import torch

    from fitting.data import TrainingSet

    def view(width):
        mask = np.zeros((20, width), np.float32)
        mask[5:15, width - 6 : width - 2] = 1  # the body at the right edge: the box would reach the padding
        camera = SimpleNamespace(K=np.eye(3), cam_from_world=np.eye(4))
        return SimpleNamespace(
            image=np.ones((20, width, 3), np.float32), mask=mask, band=np.zeros((20, width), bool), camera=camera
        )

    poses = SimpleNamespace(to=lambda device: None)
    training = TrainingSet([view(30), view(40)], [0, 1], poses, torch.device("cpu"))
    assert (training.height, training.width) == (20, 40)
    batch = training.sample(16, 64, 0.5, 0.25, torch.Generator().manual_seed(0))
    narrow = batch.frames == 0  # the 30-px view is frame 0
    columns = batch.dirs[:, 0] / batch.dirs[:, 2]  # K = I: the column of each ray
    assert len(columns) == 1024 and (columns[narrow] < 30).all(), "the 30-px view samples only its own columns"


def test_the_floor_is_found_under_the_feet_or_given(recording, prepared, tmp_path, capsys):
    found = ZjuCapture(prepared).floor
    # the synthetic world is z-down with the feet on z = 0 in every frame; the cameras on a ring give up = -z to
    # within their tilt's leftover (4 cameras), and the fitted feet sit within the fit's few cm of the true ones
    assert found.source == "feet" and np.degrees(np.arccos(found.up @ [0, 0, -1])) < 3.0
    assert abs(found.height) < 0.03
    report = json.loads((prepared / "report.json").read_text())["floor"]
    assert abs(report["lowest_point_cm_median"]) < 1e-6, "the median frame's lowest point defines the floor"
    # a short body fit: the given floor is written as given, whatever the bodies
    short = ["--fit-iterations", "100", "--silhouette-iterations", "50"]
    assert _prepare(recording / "rec", tmp_path / "given", "--floor", "z-down=0.01", *short) == 0
    given = ZjuCapture(tmp_path / "given").floor
    assert given.source == "given" and list(given.up) == [0, 0, -1] and given.height == -0.01
    stage = stage_of(np.array([0, 0, 1.0]), np.zeros((1, 4, 3)), np.zeros((1, 3)), np.zeros((1, 3)), given)
    assert stage.floor == -0.01 and list(stage.up) == [0, 0, -1], "a motion is placed on the capture's floor"
    capsys.readouterr()
    with pytest.raises(SystemExit) as usage:  # argparse's usage error: the usage line, then one error line
        prepare_capture.main([str(recording / "rec"), "--out", str(tmp_path / "bad"), "--floor", "down"])
    assert usage.value.code == 2 and "argument --floor: expected 'auto'" in capsys.readouterr().err.splitlines()[-1]
    assert not (tmp_path / "bad").exists()


def test_camera_names_match_up_to_case_separators_and_padding():
    """Pose2Sim names a camera ``cam_01`` in its calibration and ``cam01.mp4`` on disk: matched by name, whatever
    the order; the report says how; a recording behind two cameras through --camera-map is refused."""
    from types import SimpleNamespace

    from pipelines.datasets.errors import CaptureError
    from pipelines.prepare.sources.recordings import Source, match_cameras, name_key

    assert {name_key(n) for n in ("cam_01", "cam01", "Cam1", "CAM-001", "cam 1")} == {"cam1"}
    assert name_key("cam10") != name_key("cam1")
    cameras = [SimpleNamespace(name=n) for n in ("cam_01", "cam_02", "cam_10")]
    sources = [Source(n, Path(f"{n}.mp4"), True) for n in ("cam10", "cam2", "Cam01", "extra")]
    matched = match_cameras(cameras, sources)
    assert [(c.name, s.name) for c, s, _ in matched] == [("cam_01", "Cam01"), ("cam_02", "cam2"), ("cam_10", "cam10")]
    assert {how for _, _, how in matched} == {"name, up to case, separators and zero padding"}
    # two recordings with one key are not guessed between: counts differ, so no order rule either
    with pytest.raises(CaptureError, match="give --camera-map"):
        match_cameras(cameras[:1], [Source(n, Path(n), True) for n in ("cam1", "cam_1")])
    with pytest.raises(CaptureError, match="only camera 'cam_02' .* has a recording .cam2.mp4."):
        match_cameras(cameras, [sources[1]])
    pairs = match_cameras(cameras[:2], [Source(n, Path(n), True) for n in ("a", "b")])
    assert [how for _, _, how in pairs] == ["order (natural sort of both)"] * 2
    with pytest.raises(CaptureError, match="recording cam2 behind several cameras .cam_01, cam_02."):
        match_cameras(cameras, sources, {"cam_01": "cam2", "cam_02": "cam2"})


def test_what_the_capture_leaves_out_is_said(recording, tmp_path, capsys):
    """A recording without a calibrated camera, a camera with fewer frames and a 1-frame capture are each said in the
    printed summary and in report.json (``notices``)."""
    from fitting.video import write_mp4
    from pipelines.prepare.sources.recordings import read_frames

    rec = tmp_path / "rec"
    shutil.copytree(recording / "rec", rec)
    shutil.copy(rec / "videos" / "Camera_B1.mp4", rec / "videos" / "Extra.mp4")
    short = [frame[..., ::-1] for _, frame in read_frames(_source(rec / "videos" / "Camera_B4.mp4"), range(8))]
    write_mp4(rec / "videos" / "Camera_B4.mp4", short, fps=25)
    flags = ["--keypoints", rec / "keypoints", "--masks", rec / "masks", "--silhouette-iterations", "0"]
    capsys.readouterr()
    argv = [str(a) for a in [rec, "--out", tmp_path / "out", *flags, "--quiet"]]
    assert run_cli("narf-prepare-capture", prepare_capture.main, argv) == 0
    printed = capsys.readouterr().out
    notices = json.loads((tmp_path / "out" / "report.json").read_text())["notices"]
    assert notices[:3] == [
        "recordings without a calibrated camera, left out: Extra",
        "cameras with fewer frames (Camera_B4 8 of 10): the capture keeps the 8 all share",
        "the videos' frame rates differ (Camera_B1 30, Camera_B2 30, Camera_B3 30, Camera_B4 25 fps): frames are "
        "paired by index, so check the sync",
    ]
    assert all(f"note: {n}" in printed for n in notices)
    argv = [str(a) for a in [rec, "--out", tmp_path / "one", *flags, "--frames", "0:1", "--quiet"]]
    assert run_cli("narf-prepare-capture", prepare_capture.main, argv) == 0
    notices = json.loads((tmp_path / "one" / "report.json").read_text())["notices"]
    assert "1 frame(s) kept: no novel-pose frames (splits.json novel_frames is empty)" in notices


def _source(path):
    from pipelines.prepare.sources.recordings import Source

    return Source(path.stem, path, True)


def test_bodies_users_bring_are_taken_as_given(recording, tmp_path, capsys):
    """ZJU params/ and EasyMocap's per-frame JSON (a list, or {"annots": [...]}, several people) replace the body fit:
    with the silhouette stage off, the capture's bodies are the given ones; bad folders are one line each."""
    truth = ZjuCapture(recording / "truth")
    rec = recording / "rec"
    flags = ["--keypoints", rec / "keypoints", "--masks", rec / "masks", "--silhouette-iterations", "0", "--quiet"]

    def prepare(out, *extra):
        return run_cli(
            "narf-prepare-capture", prepare_capture.main, [str(a) for a in [rec, "--out", out, *flags, *extra]]
        )

    easymocap = tmp_path / "smpl"
    easymocap.mkdir()
    for f in range(truth.n_frames):
        p = truth.params(f)
        ours = {
            "id": 3,
            "Rh": [p.rh.tolist()],
            "Th": [p.th.tolist()],
            "poses": [p.poses.tolist()],
            "shapes": [p.shapes.tolist()],
        }
        other = {**ours, "id": 7, "Th": [[9.0, 9.0, 9.0]]}
        people = [other, ours] if f % 2 else {"annots": [ours, other]}
        (easymocap / f"{f:06d}.json").write_text(json.dumps(people))
    for folder, extra in ((recording / "truth" / "params", []), (easymocap, ["--person", "3"])):
        out = tmp_path / f"out_{folder.name}"
        assert prepare(out, "--smpl-params", folder, *extra) == 0
        capture = ZjuCapture(out)
        for f in range(truth.n_frames):
            a, b = truth.params(f), capture.params(f)
            # float32 files both ways; Rh goes through one rotation-vector composition
            np.testing.assert_allclose(b.poses[3:], a.poses[3:], atol=1e-6)
            np.testing.assert_allclose(
                Rotation.from_rotvec(b.rh).as_matrix(), Rotation.from_rotvec(a.rh).as_matrix(), atol=1e-5
            )
            np.testing.assert_allclose(b.th, a.th, atol=1e-6)
    assert "several people" not in capsys.readouterr().err

    def refused(extra, message):
        assert message in prepare_error(capsys, [rec, "--out", tmp_path / "x", *flags, *extra])

    refused(["--smpl-params", easymocap], "000000.json: 2 people (ids [3, 7]); choose one with --person ID")
    refused(["--smpl-params", easymocap, "--person", "5"], "no person with id 5")
    refused(["--person", "3"], "give --smpl-params too")
    broken = tmp_path / "broken"
    shutil.copytree(easymocap, broken)
    (broken / "000004.json").unlink()
    refused(["--smpl-params", broken, "--person", "3"], "no body for 1 of the 10 frames kept (first: frame 4)")
    shutil.copy(easymocap / "000004.json", broken)
    shape16 = json.loads((easymocap / "000000.json").read_text())
    shape16["annots"][0]["shapes"] = [[0.0] * 16]
    (broken / "000000.json").write_text(json.dumps(shape16))
    refused(["--smpl-params", broken, "--person", "3"], "16 shape values; SMPL's are 10")
    text = [{"id": 3, "Rh": "up", "Th": [0, 0, 0], "poses": [0] * 72, "shapes": [0] * 10}]
    (broken / "000000.json").write_text(json.dumps(text))
    refused(["--smpl-params", broken, "--person", "3"], "'Rh' holds something other than numbers")


def test_keypoint_files_without_masks_take_the_segmenters_mask(tmp_path):
    """--keypoints without --masks: the keypoints come from the files and the masks from the segmenter (an empty
    mask would flag every camera), also for a frame that has no keypoint file; the detector's person comes with the
    mask as its owner (``follow_person`` checks whose mask it is)."""
    from pipelines.prepare.sources.observe import _Keypoints

    write_openpose(tmp_path / "cam01_json" / "cam01.0000.json", [np.ones((25, 3))])
    mask = np.zeros((4, 6), bool)
    mask[1:3, 2:4] = True
    calls = []

    detected = np.zeros((33, 3))
    detected[11] = (5.0, 2.0, 0.9)  # BlazePose's left shoulder: the l_shoulder target

    def segmenter(rgb):
        calls.append(rgb.shape)
        return detected, mask

    found = _Keypoints(tmp_path, "cam01", lambda frame, rgb: segmenter(rgb), "body25", need_mask=True)
    targets, got, owner = found(0, np.zeros((4, 6, 3), np.uint8), 1.0)
    assert len(targets) == 1 and got is mask
    np.testing.assert_array_equal(owner, to_targets(detected, "blazepose"))
    again = found(1, np.zeros((4, 6, 3), np.uint8), 1.0)
    assert again[0] == [] and again[1] is mask and again[2] is not None and len(calls) == 2
    plain = _Keypoints(tmp_path, "cam01", lambda frame, rgb: segmenter(rgb), "body25")
    assert plain(0, np.zeros((4, 6, 3), np.uint8), 1.0)[1:] == (None, None)
    nobody = _Keypoints(tmp_path, "cam01", lambda frame, rgb: (None, None), "body25", need_mask=True)
    owner = nobody(0, np.zeros((4, 6, 3), np.uint8), 1.0)[2]  # nobody found: nobody's targets, all unseen
    assert owner.shape == (len(TARGET_JOINTS), 3) and not owner.any()
    alone = _Keypoints(tmp_path, "cam01", lambda frame, rgb: (None, mask), "body25", need_mask=True)
    assert alone(0, np.zeros((4, 6, 3), np.uint8), 1.0)[2] is None  # a mask without a detection: whose is unknown


def test_two_preparations_are_compared_frame_by_frame(prepared, tmp_path):
    """The same capture with every vertex moved 1 cm: its bodies lie exactly 1 cm from the original's (float32
    vertices of a body within 2 m: the distance is exact to ~1e-5 cm), and each capture's fit is reported as is."""
    from pipelines.prepare.compare import compare_captures

    moved = tmp_path / "moved"
    shutil.copytree(prepared, moved)
    for path in (moved / "vertices").glob("*.npy"):
        np.save(path, np.load(path) + np.float32([0.0, 0.006, 0.008]))
    result = compare_captures(prepared, moved)
    distance = result["body_distance"]
    assert distance["frames"] == json.loads((prepared / "report.json").read_text())["frames"]["kept"]
    for key in ("median_cm", "mean_cm", "p95_cm"):
        assert abs(distance[key] - 1.0) < 1e-4, distance
    assert set(result["fit"]) == {str(prepared), str(moved)}
    with pytest.raises(CaptureError, match="report.json"):
        compare_captures(prepared, tmp_path)


def _started_late(rec: Path, out: Path, camera: str, late: int) -> Path:
    """A copy of recording ``rec`` whose ``camera`` started ``late`` frames after the others: its video, keypoint
    files and masks lose their first ``late`` frames and are numbered from 0 again."""
    from fitting.video import write_mp4
    from pipelines.prepare.sources.recordings import Source, read_frames

    shutil.copytree(rec, out)
    video = out / "videos" / f"{camera}.mp4"
    frames = [bgr[..., ::-1] for _, bgr in read_frames(Source(camera, video, True), range(late, 10**9))]
    video.unlink()
    write_mp4(video, frames, fps=30)
    keypoints, masks = out / "keypoints" / f"{camera}_json", out / "masks" / camera
    for folder, name in ((keypoints, lambda f: f"{camera}_{f:012d}_keypoints.json"), (masks, lambda f: f"{f:06d}.png")):
        count = len(list(folder.iterdir()))
        for f in range(count):
            if f < late:
                (folder / name(f)).unlink()
            else:
                (folder / name(f)).rename(folder / name(f - late))
    return out


def test_a_camera_started_late_is_put_in_step(recording, prepared, tmp_path, capsys):
    """cam 2 of the synthetic recording started 3 frames late: its offset is found as +3 (below a frame: within 0.5),
    its frames are shifted, and the capture's bodies equal the in-step capture's on the frames both hold, within what
    the keypoint noise leaves (1 px at 256 px: the bodies of two preparations of the same frames differ by a few mm);
    reprojection is as in step. ``--sync off`` leaves the camera 3 frames out of step, and it shows. A camera out of
    step spoils the triangulation the others are judged by, so the others' first estimates are off by frames too
    (cam 1 at -2.3 here): only cam 2 may be shifted."""
    names = sorted(p.stem for p in (recording / "rec" / "videos").glob("*.mp4"))
    late = _started_late(recording / "rec", tmp_path / "rec", names[2], 3)
    assert _prepare(late, tmp_path / "out", "--sync", "auto") == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    entry = report["sync"]["cameras"][names[2]]
    assert entry["applied_frames"] == 3 and abs(entry["offset_frames"] - 3) <= 0.5, entry
    # the silhouettes' second look needs each scored frame seen at every offset within 3 of the keypoints' shift:
    # on 10 frames too few are (sync_silhouettes.MIN_FRAMES), so there is none (tests/test_sync_silhouettes.py)
    assert all("silhouettes" not in e for e in report["sync"]["cameras"].values()), report["sync"]
    assert all(report["sync"]["cameras"][n]["applied_frames"] == 0 for n in names if n != names[2]), report["sync"]
    assert "time offsets in frames (auto)" in capsys.readouterr().out
    in_step = json.loads((prepared / "report.json").read_text())
    # the default (auto) estimates, finds the in-step recording in step, and shifts nothing
    assert in_step["sync"]["mode"] == "auto"
    in_step_cameras = in_step["sync"]["cameras"].values()
    assert all(e["status"] == "in step" and e["applied_frames"] == 0 for e in in_step_cameras), in_step["sync"]
    assert report["frames"]["source_frames"] == in_step["frames"]["source_frames"][3:]
    a, b = ZjuCapture(prepared), ZjuCapture(tmp_path / "out")
    for i in range(b.n_frames):
        distance = np.linalg.norm(a.vertices(i + 3) - b.vertices(i), axis=-1)
        assert np.median(distance) < 0.01, (i, float(np.median(distance)))
    reprojection = "median_reprojection_pct_height"
    assert report["summary"][reprojection] < 1.2 * in_step["summary"][reprojection]
    # out of step, with a short silhouette stage: the keypoints' reprojection shows the offset at any length of it
    assert _prepare(late, tmp_path / "off", "--sync", "off", "--silhouette-iterations", "100") == 0
    off = json.loads((tmp_path / "off" / "report.json").read_text())
    assert off["sync"]["mode"] == "off"
    # the robust triangulation and the body fit absorb part of it: measured 1.42 x the in-step capture's
    assert off["summary"][reprojection] > max(1.3 * in_step["summary"][reprojection], report["summary"][reprojection])


def test_sync_flag_refuses_bad_values(recording, tmp_path, capsys):
    """``--sync`` takes auto, report, off or CAM=FRAMES: another word or a fraction is argparse's usage error (exit 2,
    the error on the last line); a camera the rig does not have is one line, exit 2, before anything is written."""
    for value in ("sometimes", "cam1=1.5"):
        capsys.readouterr()
        with pytest.raises(SystemExit) as stop:
            _prepare(recording / "rec", tmp_path / "x", "--sync", value)
        err = capsys.readouterr().err.strip().splitlines()
        assert stop.value.code == 2 and "argument --sync: expected auto, report, off or CAM=FRAMES" in err[-1], err
    assert _prepare(recording / "rec", tmp_path / "y", "--sync", "nosuchcam=2") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nosuchcam not among the cameras" in err[0], err
    assert not (tmp_path / "y").exists()


def test_openpose_entries_with_no_keypoints_are_no_person(tmp_path):
    """OpenPose writes people whose ``pose_keypoints_2d`` is empty (a person found by its face or hands alone): such an
    entry is skipped, the other people are read as they are, and a file of only such entries has no person."""
    person = np.column_stack([np.arange(25.0), np.arange(25.0) + 1, np.full(25, 0.9)])
    path = tmp_path / "cam_000000000000_keypoints.json"
    people = [{"pose_keypoints_2d": []}, {"pose_keypoints_2d": person.ravel().tolist()}, {"pose_keypoints_2d": []}]
    path.write_text(json.dumps({"version": 1.3, "people": people}))
    found = read_openpose(path)
    assert len(found) == 1 and np.array_equal(found[0], person)
    path.write_text(json.dumps({"version": 1.3, "people": [{"pose_keypoints_2d": []}]}))
    assert read_openpose(path) == []


def test_a_cameras_folder_is_never_another_cameras(tmp_path):
    """Keypoint and mask folders are found by the camera's name followed by a separator: ``cam1``'s is ``cam1_json``,
    never ``cam10_json`` (which sorts first); two candidates are an error naming both."""
    from pipelines.prepare.sources.observe import camera_folder

    for name in ("cam10_json", "cam1_json", "cam12_json", "cam2"):
        (tmp_path / name).mkdir()
    assert camera_folder(tmp_path, "cam1").name == "cam1_json"
    assert camera_folder(tmp_path, "cam10").name == "cam10_json"
    assert camera_folder(tmp_path, "cam2").name == "cam2"
    with pytest.raises(CaptureError, match="no sub-folder for camera 'cam3'"):
        camera_folder(tmp_path, "cam3")
    (tmp_path / "cam1-masks").mkdir()
    with pytest.raises(CaptureError, match="cam1-masks, cam1_json"):
        camera_folder(tmp_path, "cam1")


def test_cameras_that_agree_are_not_flagged_and_a_poor_capture_is_a_notice():
    """The 64-px probe's figures (docs/results/faults.md): four cameras at 1.77-1.85 % of the image height, all
    above the 1.5 % threshold, agree with each other: none is flagged, and the report carries one notice. A camera
    standing 1.3 times above the others is flagged; one 3 times above small others is flagged by the ratio; with no
    other camera to compare, the absolute threshold alone. (Checked against the absolute threshold alone: every
    camera of the probe was flagged.)"""
    from pipelines.prepare.layout.checks import FLAG_ERROR, flag_cameras, reprojection_notice

    names = ["A", "B", "C", "D"]
    agree = dict(zip(names, [0.0177, 0.0179, 0.0181, 0.0185]))
    none = {n: 0.0 for n in names}
    ious = {n: 0.9 for n in names}
    assert flag_cameras(names, agree, ious, none) == {}
    notice = reprojection_notice(agree)
    assert notice is not None and "1.77-1.85 %" in notice
    assert reprojection_notice(dict(zip(names, [0.005, 0.006, 0.007, 0.02]))) is None  # the median is 0.65 %
    apart = {**agree, "D": 0.024}  # 1.33 x the others' median 1.79 %
    assert list(flag_cameras(names, apart, ious, none)) == ["D"]
    small = dict(zip(names, [0.003, 0.003, 0.003, 0.009]))  # 3 x, under 1.5 %
    assert list(flag_cameras(names, small, ious, none)) == ["D"]
    assert list(flag_cameras(["A"], {"A": FLAG_ERROR + 0.001}, {"A": 0.9}, {"A": 0.0})) == ["A"]
