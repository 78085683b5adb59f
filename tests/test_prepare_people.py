"""narf-prepare-capture with somebody else in view (docs/guides/real-captures.md, *Other people in view*): the
synthetic recording with a second person walking past, in the keypoint files (first in each file) and the masks of
the cameras that see them. The capture follows the person seen best, leaves the other out of its masks, flags no
camera, and ``--person`` picks the other one."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipelines.body.model import BodyModel
from pipelines.cli import prepare_capture
from pipelines.cli.common import run_cli
from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.keypoints import TARGET_JOINTS, read_openpose
from pipelines.synthetic.recording import add_passer_by, true_joints

#: the second person's path: 1.8 m beside the first, walking 0.3 m a frame across the room (world x, y horizontal)
OFFSET, STEP = np.array([-1.4, 1.8, 0.0]), np.array([0.3, 0.0, 0.0])


@pytest.fixture(scope="module")
def crowded(recording, tmp_path_factory):
    root = tmp_path_factory.mktemp("crowded")
    shutil.copytree(recording / "rec", root / "rec")
    passer = add_passer_by(recording / "truth", root / "rec", OFFSET, STEP)
    return root, passer


def _prepare(rec, out, *extra) -> int:
    """narf-prepare-capture with 100 silhouette iterations (400 by default): whom the capture follows is settled
    before that stage, and the bodies (and the masks cut around them) meet the bounds below after 100."""
    argv = [str(rec), "--out", str(out), "--keypoints", str(rec / "keypoints"), "--masks", str(rec / "masks")]
    return run_cli(
        "narf-prepare-capture", prepare_capture.main, [*argv, "--quiet", "--silhouette-iterations", "100", *extra]
    )


def _crowded_capture(root: Path) -> Path:
    """The crowded recording prepared once into ``root/out``, whichever test asks first (the tests run in any
    order)."""
    if not (root / "out" / "report.json").is_file():
        assert _prepare(root / "rec", root / "out") == 0
    return root / "out"


def _error_cm(capture, joints) -> np.ndarray:
    return 100 * np.linalg.norm(np.load(capture / "keypoints3d.npy") - joints[:, list(TARGET_JOINTS)], axis=-1)


def test_the_capture_follows_the_person_seen_best(recording, crowded):
    root, passer = crowded
    truth = ZjuCapture(recording / "truth")
    _crowded_capture(root)
    report = json.loads((root / "out" / "report.json").read_text())
    files = sorted((root / "rec" / "keypoints").glob("*/*.json"))
    two = sum(len(read_openpose(path)) == 2 for path in files)
    assert two >= 2 * 10 and two < len(files)  # the passer-by is in two or more views of each frame, not in all
    assert report["person"]["people_seen"] == 2, report["person"]
    assert report["person"]["frames_sides_turned"] == []  # the files label every side right
    assert report["frames"]["kept"] == 10 and not report["flagged_cameras"]
    # as the one-person capture (tests/test_prepare_capture.py): 1 px of noise is about 1 cm at these cameras
    error_cm = _error_cm(root / "out", true_joints(truth, BodyModel()))
    assert np.median(error_cm) < 2.0 and error_cm.max() < 6.0, error_cm
    out, apart_views, near, near_kept = ZjuCapture(root / "out", mask_source="mask"), 0, 0, 0
    for f in range(out.n_frames):
        for camera in out.cameras:
            given = cv2.imread(str(root / "rec" / "masks" / camera.name / f"{f:06d}.png"), 0) > 0
            kept = cv2.imread(str(root / "out" / "mask" / camera.name / f"{f:06d}.png"), 0) > 0
            true = cv2.imread(str(recording / "truth" / "mask" / camera.name / f"{f:06d}.png"), 0) > 0
            # where the passer-by stands apart from the first person in the image (farther than the neighbourhood
            # the capture's masks keep around the fitted body, people.occlusion.body_neighbourhood: 4 % of the height,
            # plus 2 px of the fit's error), none of them is kept
            distance = cv2.distanceTransform((~true).astype(np.uint8), cv2.DIST_L2, 5)
            passer = given & ~true
            if passer.any() and distance[passer].min() > 0.04 * camera.height + 2:
                apart_views += 1
                assert not (kept & passer).any(), (f, camera.name)
            close = passer & (distance <= 0.04 * camera.height + 2)
            near, near_kept = near + close.sum(), near_kept + (kept & close).sum()
    assert apart_views >= 5  # 7 of the 40 views, by the passer-by's path (OFFSET, STEP)
    # near the person, the passer-by's pixels leave the masks but where the fitted body covers them (it may be either
    # person there) or where the capsules drawn for the passer-by miss their silhouette
    # (pipelines.prepare.people.occlusion): 11 % of them stay (93 % with the cut removed, which this bound, between the
    # two, tells apart)
    assert near_kept < 0.25 * near, (near_kept, near)
    # views where the passer-by covers over a quarter of the person (4 of 40 measured; a share near the threshold may
    # tip either way with the triangulation's rounding on another CPU): some, not most
    assert 1 <= report["person"]["views_overlapped_by_others"] <= 10


@pytest.mark.parametrize("how", ["near", "pixel"])
def test_person_picks_the_other_one(recording, crowded, tmp_path, how):
    """``--person near:X,Y,Z`` (the passer-by's pelvis half-way) and ``pixel:CAM:U,V`` (their pelvis in the first
    frame, in a camera that sees them) follow the passer-by."""
    root, passer = crowded
    if how == "near":
        choice = "near:" + ",".join(f"{v:.3f}" for v in passer[5, 0])
    else:
        from pipelines.datasets.camera import project_distorted

        camera = next(c for c in ZjuCapture(recording / "truth").cameras if _inside(c, project_distorted(c, passer[0])))
        u, v = project_distorted(camera, passer[0, :1])[0]
        choice = f"pixel:{camera.name}:{u:.1f},{v:.1f}"
    assert _prepare(root / "rec", tmp_path / "other", "--person", choice) == 0
    report = json.loads((tmp_path / "other" / "report.json").read_text())
    assert "nearest" in report["person"]["followed"]
    kept = report["frames"]["source_frames"]
    error_cm = _error_cm(tmp_path / "other", passer[kept])
    # seen by two or three of the four cameras, where the first person is seen by four: each joint's triangulation
    # rests on fewer views than the 2 cm of the first person's (measured 2.3 cm)
    assert len(kept) >= 3 and np.median(error_cm) < 3.0, (kept, np.median(error_cm))


def _inside(camera, pixels: np.ndarray) -> bool:
    return bool(((pixels >= 0) & (pixels < [camera.width, camera.height])).all())


RED, GREEN = np.array([220, 30, 30]), np.array([30, 220, 30])


def test_a_view_that_shows_somebody_else_is_detected_again_around_the_person(recording, tmp_path):
    """One view where a second person stands nearer the camera, beside the first: a detector that finds the most
    prominent person (here: the largest blob of one colour) finds the second one in the whole image, and in a box
    around the first with the second painted out, the first; without the painting, the second again."""
    from types import SimpleNamespace

    from pipelines.datasets.camera import project_distorted, silhouette
    from pipelines.datasets.keypoints import keypoints_from_joints, to_targets
    from pipelines.prepare.people.crops import crop_box, painted_crop, redetect
    from pipelines.prepare.sources.detections import CachedDetector

    truth, body = ZjuCapture(recording / "truth"), BodyModel()
    camera, joints = truth.cameras[0], true_joints(truth, body)[0]
    toward = camera.centre - joints[0]
    toward[2] = 0  # horizontal (world z is up or down in the synthetic rig)
    shift = 0.35 * toward + 0.5 * np.cross(toward / np.linalg.norm(toward), [0, 0, 1])
    people = {"first": (joints, truth.vertices(0)), "second": (joints + shift, truth.vertices(0) + shift)}
    image = np.full((camera.height, camera.width, 3), 90, np.uint8)
    for (_, vertices), colour in zip(people.values(), (RED, GREEN)):
        image[silhouette(camera, vertices, body.faces)] = colour
    pixels = {name: project_distorted(camera, j) for name, (j, _) in people.items()}
    corner = {}

    def blob(rgb, colour):
        return np.abs(rgb.astype(int) - colour).sum(-1) < 60  # the colours, through JPEG

    def most_prominent(rgb):
        sizes = {name: blob(rgb, c).sum() for name, c in zip(people, (RED, GREEN))}
        name = max(sizes, key=sizes.get)
        offset = np.argwhere(blob(rgb, (RED, GREEN)[list(people).index(name)])).min(0)[::-1] - corner[name]
        return keypoints_from_joints(pixels[name] + offset, "blazepose"), None

    folder = tmp_path / "frames"
    (folder / camera.name).mkdir(parents=True)
    cv2.imwrite(str(folder / camera.name / "000000.jpg"), image[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])
    decoded = cv2.imread(str(folder / camera.name / "000000.jpg"))[..., ::-1]
    for name, colour in zip(people, (RED, GREEN)):
        corner[name] = np.argwhere(blob(decoded, colour)).min(0)[::-1]  # (x, y) of the blob's top-left, whole image
    seen_targets = to_targets(keypoints_from_joints(pixels["first"], "blazepose"), "blazepose")[:, 2] > 0
    whole = to_targets(most_prominent(decoded)[0], "blazepose")
    expected = {
        n: to_targets(keypoints_from_joints(p, "blazepose"), "blazepose")[seen_targets, :2] for n, p in pixels.items()
    }
    np.testing.assert_allclose(whole[seen_targets, :2], expected["second"], atol=1e-6)  # the whole image: the second
    box = crop_box(camera, joints[list(TARGET_JOINTS)])
    crop = decoded[box[1] : box[3], box[0] : box[2]]
    assert blob(crop, GREEN).sum() > blob(crop, RED).sum()  # the box alone still shows the second one larger
    seen = SimpleNamespace(cameras=[camera], people=[{0: [whole]}])
    route = {0: _world_targets(joints)}
    crops = {}
    cache = CachedDetector(most_prominent, tmp_path / "cache", "fake")
    others = {0: [_world_targets(joints + shift)]}
    assert redetect(folder, seen, route, crops, cache, 0.03, others) == 1
    # the first person, placed through the box's corner exactly (the blob's edge is the same pixels in both)
    np.testing.assert_allclose(seen.people[0][0][0][seen_targets, :2], expected["first"], atol=1e-6)
    assert list(crops) == [(0, 0)] and crops[(0, 0)][0][0] == box
    painted = painted_crop(decoded, box, camera, route[0], others[0])
    assert blob(painted, GREEN).sum() < blob(painted, RED).sum()


def _world_targets(joints: np.ndarray) -> np.ndarray:
    return joints[list(TARGET_JOINTS)]


def test_keypoint_files_with_people_in_any_order_and_a_false_one(recording, crowded, tmp_path):
    """OpenPose-style files as a detector writes them for a crowded scene: the people of each file in an order that
    changes from frame to frame, and a false third person in some files (four points at confidence 0.2, scattered).
    The capture follows the same person as from the files in order, no camera flagged, and its joints lie within
    3 cm of that capture's (1 px of keypoint noise is about 1 cm at these cameras)."""
    from pipelines.datasets.keypoints import write_openpose

    root, _ = crowded
    shuffled = tmp_path / "rec"
    shutil.copytree(root / "rec", shuffled)
    rng = np.random.default_rng(7)
    for path in sorted((shuffled / "keypoints").glob("*/*.json")):
        people = read_openpose(path)
        if rng.random() < 0.5:
            false = np.zeros_like(people[0])
            points = np.column_stack([rng.uniform(0, 256, (4, 2)), np.full(4, 0.2)])
            false[rng.choice(len(false), 4, replace=False)] = points  # four scattered points
            people.append(false)
        write_openpose(path, [people[i] for i in rng.permutation(len(people))])
    _crowded_capture(root)
    assert _prepare(shuffled, tmp_path / "out") == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["frames"]["kept"] == 10 and not report["flagged_cameras"], report["flagged_cameras"]
    apart = 100 * np.linalg.norm(
        np.load(tmp_path / "out" / "keypoints3d.npy") - np.load(root / "out" / "keypoints3d.npy"), axis=-1
    )
    assert np.median(apart) < 3.0, apart


def _blazepose(targets: np.ndarray) -> np.ndarray:
    """(33, 3) BlazePose keypoints that give ``targets`` back through ``to_targets`` (each target's points on it)."""
    from pipelines.datasets.keypoints import TARGETS

    keypoints = np.zeros((33, 3))
    for t, target in enumerate(TARGETS):
        for index in target.sources.get("blazepose", ()):
            keypoints[index] = targets[t]
    return keypoints


@pytest.mark.slow
def test_keypoint_files_with_the_segmenters_mask_of_somebody_else(recording, crowded, tmp_path, monkeypatch):
    """--keypoints without --masks: each view's mask is the segmenter's, of whomever the detector found. In five views
    of one camera the detector finds the passer-by, with a mask over the whole image, and in a box around the
    followed person nobody: those views are detected again and left out (their mask is somebody else's), and the
    camera's body-vs-mask IoU stays that of true masks in every view (0.94 measured; 0.9 leaves room for 1 px of
    keypoint noise). Keeping them (the mask taken as the followed person's) gave 0.41 in the worst view."""
    import hashlib

    import pipelines.prepare.sources.detect as detect
    from pipelines.datasets.keypoints import to_targets
    from pipelines.prepare.sources.recordings import find_sources, read_frames

    root, _ = crowded
    table, wrong = {}, 0
    for source in find_sources(root / "rec"):
        files = sorted((root / "rec" / "keypoints" / f"{source.name}_json").glob("*.json"))
        for (frame, bgr), path in zip(read_frames(source, range(10**9)), files):
            people = [to_targets(p, "body25") for p in read_openpose(path)]  # the passer-by first, where in view
            mask = cv2.imread(str(recording / "rec" / "masks" / source.name / f"{frame:06d}.png"), 0) > 0
            if source.name == "Camera_B1" and len(people) == 2 and wrong < 5:
                wrong, answer = wrong + 1, (_blazepose(people[0]), np.ones_like(mask))
            else:
                answer = (_blazepose(people[-1]), mask)
            table[hashlib.sha256(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).tobytes()).hexdigest()] = answer
    assert wrong == 5
    monkeypatch.setattr(
        detect, "BlazePose", lambda *_: lambda rgb: table.get(hashlib.sha256(rgb.tobytes()).hexdigest(), (None, None))
    )
    monkeypatch.setattr(detect, "detector_id", lambda *_: "the files' people")
    argv = [str(root / "rec"), "--out", str(tmp_path / "out"), "--keypoints", str(root / "rec" / "keypoints")]
    assert run_cli("narf-prepare-capture", prepare_capture.main, [*argv, "--quiet"]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    # each of the five is left out: for its mask, or before its mask is looked at where the passer-by overlaps the
    # person in the image (pipelines.prepare.people.occlusion), which leaves out views of the camera's other five too
    without, overlapped = report["person"]["views_without_their_mask"], report["cameras"]["Camera_B1"]
    overlapped = overlapped["views_overlapped_by_others"]
    assert report["person"]["views_detected_again"] == 5 and without <= 5 <= without + overlapped
    assert not report["flagged_cameras"] and report["cameras"]["Camera_B1"]["views_used"] == 10 - without - overlapped
    assert report["cameras"]["Camera_B1"]["iou_min"] > 0.9


def test_keypoint_files_with_a_person_the_videos_do_not_show(recording, crowded, tmp_path):
    """Keypoint files that also hold a person who stands still in no video (a take's other version, a detector's
    false person), while the person of the videos is missing from two files of each camera: no view's mask shows
    the first, so they are dropped before anybody is chosen and the report counts them; the capture follows the
    person of the videos, no camera flagged. (Checked against the tracks as the files give them: the count was
    missing. This rig's stand-still person is seen by fewer agreeing views than the person of the videos, so it
    does not reproduce the demo's choice of the person of no video; the mask check is what excludes them.)"""
    from pipelines.datasets.keypoints import write_openpose
    from pipelines.synthetic.recording import add_passer_by

    rec = tmp_path / "rec"
    shutil.copytree(recording / "rec", rec)
    add_passer_by(recording / "truth", rec, np.array([0.0, 1.6, 0.0]), np.zeros(3))  # keypoints and masks
    shutil.rmtree(rec / "masks")
    shutil.copytree(recording / "rec" / "masks", rec / "masks")  # the masks of the videos: the true person's only
    for k, folder in enumerate(sorted((rec / "keypoints").iterdir())):  # the true person (last in the file) missing
        for path in sorted(folder.glob("*.json"))[2 * k : 2 * k + 2]:  # from two views of each camera, 8 in all
            write_openpose(path, read_openpose(path)[:1])
    assert _prepare(rec, tmp_path / "out") == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    error_cm = _error_cm(tmp_path / "out", true_joints(ZjuCapture(recording / "truth"), BodyModel()))
    assert np.median(error_cm) < 2.0, error_cm  # the person of the videos, as the one-person capture above
    assert report["person"]["people_without_mask"] == 1 and report["person"]["people_seen"] == 1
    assert not report["flagged_cameras"]
