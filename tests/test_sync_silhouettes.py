"""Cameras in step from the silhouettes (pipelines.prepare.sync.silhouettes): masks of spheres that walk and swing,
seen by a ring of cameras, one of them started late, one turned slightly (a calibration error)."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipelines.datasets.camera import Camera
from pipelines.prepare.sources.observe import Observations
from pipelines.prepare.sync import apply as sync_apply
from pipelines.prepare.sync import silhouettes as sync_silhouettes
from pipelines.prepare.sync.apply import METHOD_COMBINED, combined, combined_shifts
from pipelines.prepare.sync.silhouettes import inside, person_boxes, silhouette_offsets
from pipelines.synthetic.scene import look_at

N_FRAMES, SIZE = 40, 400
RADII = np.array([0.18, 0.12, 0.1, 0.1, 0.09, 0.09])


def _centres() -> np.ndarray:
    """(N, 6, 3) sphere centres: a trunk and a head that walk one way along x, stopping and starting every 14 frames
    (0-6 cm a frame), and arms and legs that swing with their own periods: the motion is mostly one way, where a
    turned camera looks most like a late one."""
    t = np.arange(N_FRAMES)[:, None]
    walked = np.cumsum(0.03 * (1 - np.cos(2 * np.pi * t[:, 0] / 14)))
    walk = (walked - walked.mean())[:, None]
    base = np.array([[0, 0, 1.1], [0, 0, 1.55], [0.0, 0.25, 1.2], [0.0, -0.25, 1.2], [0, 0.1, 0.5], [0, -0.1, 0.5]])
    swing = 0.2 * np.sin(2 * np.pi * t / np.array([1e9, 1e9, 13, 17, 11, 15]) + np.arange(6))
    centres = np.repeat(base[None], N_FRAMES, 0)
    centres[..., 0] += walk + swing
    return centres


def _rig(n: int = 4) -> list[Camera]:
    K = np.array([[360.0, 0, SIZE / 2], [0, 360.0, SIZE / 2], [0, 0, 1]])
    cameras = []
    for c in range(n):
        angle = 2 * np.pi * c / n + 0.3
        centre = np.array([4 * np.cos(angle), 4 * np.sin(angle), 1.3])
        pose = look_at(centre, np.array([0.0, 0.0, 1.0]), down=(0.0, 0.0, -1.0))
        cameras.append(Camera(f"cam{c + 1}", K, np.zeros(5), pose, SIZE, SIZE))
    return cameras


def _mask(camera: Camera, cam_from_world: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(SIZE, SIZE) bool: the pixels whose ray meets one of the spheres (centres (6, 3), ``RADII``)."""
    u, v = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
    rays = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(camera.K).T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    # the sphere in the camera's frame: |t r - c|^2 = R^2 has a root when (r . c)^2 >= |c|^2 - R^2
    in_camera = centres @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    along = rays @ in_camera.T
    hit = along**2 >= (in_camera**2).sum(1) - RADII**2
    return (hit & (along > 0)).any(1).reshape(SIZE, SIZE)


def _write_masks(folder, cameras, late: dict[int, int], turned: dict[int, float]):
    """Each camera's masks as the prepare stages them (``<camera>/<frame:06d>.png``): camera v's frame s shows the
    spheres of frame s + ``late[v]``, through its pose turned by ``turned[v]`` degrees (unknown to the estimate)."""
    centres = _centres()
    for v, camera in enumerate(cameras):
        pose = camera.cam_from_world.copy()
        if v in turned:
            pose[:3] = Rotation.from_rotvec(np.radians(turned[v]) * np.array([0.6, 0.8, 0.0])).as_matrix() @ pose[:3]
        (folder / camera.name).mkdir(parents=True)
        for s in range(N_FRAMES - late.get(v, 0)):
            mask = _mask(camera, pose, centres[s + late.get(v, 0)])
            cv2.imwrite(str(folder / camera.name / f"{s:06d}.png"), mask.astype(np.uint8))


def test_a_late_camera_is_found_and_the_others_are_in_step(tmp_path):
    cameras = _rig()
    _write_masks(tmp_path, cameras, late={2: 2}, turned={})
    found = silhouette_offsets(cameras, list(range(N_FRAMES)), tmp_path, _centres(), [0] * len(cameras))
    # within 0.4 frame: each d takes the best of translations 2 px apart (the static part), and a frame moves the
    # masks by 0-6 px here (least in the cameras that see the walk along their axis), so that choice alone can move
    # the parabola's vertex by about a third of a frame; the masks are exact
    assert found["cam3"]["whole_frames"] == 2 and abs(found["cam3"]["offset_frames"] - 2) < 0.4
    for name in ("cam1", "cam2", "cam4"):
        assert found[name]["whole_frames"] == 0 and abs(found[name]["offset_frames"]) < 0.4
    # 24 frames spread over the 40; those within REACH of the ends (or of the late camera's missing last frames)
    # cannot be scored at every d
    assert all(entry["curvature"] > 0 and entry["frames"] >= 15 for entry in found.values())


@pytest.mark.parametrize("reach", [8, 0])
def test_a_turned_camera_stays_in_step_through_the_static_part(tmp_path, monkeypatch, reach):
    """A camera turned by 1.5 degrees (9 px at this focal length: 7.5 and 5.6 px along the image's axes, within the
    8 px the translations reach) whose masks are in step: with the translations (the silhouettes' static part) it
    reads within 0.4 frame of 0, as the in-step cameras above; without them the best d is where the motion happens
    to move its mask towards the turn (the test of the test: it must read 0.6 frame off or more)."""
    monkeypatch.setattr(sync_silhouettes, "TRANSLATION_REACH", reach)
    cameras = _rig()
    _write_masks(tmp_path, cameras, late={}, turned={1: 1.5})
    found = silhouette_offsets(cameras, list(range(N_FRAMES)), tmp_path, _centres(), [0] * len(cameras))
    if reach:  # the tolerance of the test above
        assert all(abs(entry["offset_frames"]) < 0.4 for entry in found.values())
    else:
        assert abs(found["cam2"]["offset_frames"]) >= 0.6


def test_packed_masks_are_read_back_pixel_for_pixel():
    rng = np.random.default_rng(0)
    mask = rng.random((37, 53)) > 0.5  # a width that is not a multiple of 8
    packed = (np.packbits(mask.reshape(-1)), mask.shape)
    pixels = np.stack([rng.uniform(-3, 56, 500), rng.uniform(-3, 40, 500)], 1)
    xy = np.round(pixels).astype(int)  # pixel centres at whole numbers, as OpenCV projects
    on = (xy[:, 0] >= 0) & (xy[:, 1] >= 0) & (xy[:, 0] < 53) & (xy[:, 1] < 37)
    expected = np.zeros(500, bool)
    expected[on] = mask[xy[on, 1], xy[on, 0]]
    assert np.array_equal(inside(packed, pixels), expected)


def test_a_frame_with_too_few_joints_has_no_box():
    points = np.full((3, 17, 3), np.nan)
    points[0, :5] = [[0, 0, 1], [0.2, 0, 1], [0, 0.3, 1], [0, 0, 1.7], [0.1, 0.1, 0.1]]
    points[1, :3] = 0.0  # three joints only
    boxes = person_boxes(points)
    pad = sync_silhouettes.PAD
    assert np.allclose(boxes[0], [[-pad, -pad, 0.1 - pad], [0.2 + pad, 0.3 + pad, 1.7 + pad]])
    assert np.isnan(boxes[1:]).all()


def _entry(keypoints: float, whole: int, silhouettes: float, status: str = "in step") -> dict:
    look = {"offset_frames": silhouettes, "agrees": abs(silhouettes - keypoints) <= 1.0}
    return {
        "offset_frames": keypoints,
        "whole_frames": whole,
        "status": status,
        "method": "keypoints",
        "silhouettes": look,
    }


def test_the_two_looks_mean_and_the_shifts_it_asks_for():
    """Cases of the Pose2Sim demo's cut table (docs/results/real-capture.md, *Cameras in step*), by hand: a camera
    the keypoints call uncertain at -0.75 and the silhouettes put at -0.12 is in step at their mean, -0.435, and
    stays; one cut by 3 that the keypoints shifted by 2 (2.2) and the silhouettes find at 2.87 is shifted by 3; one
    cut by 2 that the keypoints left (1.2, below the capture's gain) is shifted by 2; a camera not cut that both read
    0.6-0.7 early (another camera out of step spoils its triangulation) stays; looks a frame and more apart are not
    averaged."""
    entries = {
        "in_step": combined(_entry(-0.75, 0, -0.12, status="uncertain")),
        "cut3": combined(_entry(2.2, 2, 2.87, status="out of step")),
        "cut2": combined(_entry(1.2, 0, 1.95)),
        "spoilt": combined(_entry(-0.6, 0, -0.7)),
    }
    assert entries["in_step"]["offset_frames"] == pytest.approx(-0.435, abs=0.006)  # rounded to hundredths
    assert entries["in_step"]["status"] == "in step" and entries["in_step"]["keypoints"]["offset_frames"] == -0.75
    assert entries["cut3"]["offset_frames"] == pytest.approx(2.535, abs=0.006)
    assert {e["method"] for e in entries.values()} == {METHOD_COMBINED}
    apart = _entry(-1.1, 0, 0.1)
    assert not apart["silhouettes"]["agrees"]
    assert combined_shifts({**entries, "apart": apart}) == {"cut3": 3, "cut2": 2}


def _scripted(monkeypatch, *passes):
    """``sync_apply._estimate`` answering each call with the next of ``passes`` (estimates by camera), one person in
    view."""
    answers = iter(passes)
    monkeypatch.setattr(sync_apply, "_estimate", lambda seen, folder, stride=1: (next(answers), 0.0))


def _files(tmp_path, names, n_frames=8):
    cameras = [Camera(name, np.eye(3), np.zeros(5), np.eye(4), 10, 10) for name in names]
    for name in names:
        for sub, suffix in ((tmp_path / name, "jpg"), (tmp_path / "mask_raw" / name, "png")):
            sub.mkdir(parents=True)
            for f in range(n_frames):
                (sub / f"{f:06d}.{suffix}").write_text(f"{name} {f}")
    frames = [list(range(n_frames)) for _ in names]
    return Observations(cameras, frames, [{f: [] for f in range(n_frames)} for _ in names])


def test_a_shift_the_mean_asks_for_is_made_and_estimated_again_or_undone(tmp_path, monkeypatch):
    """``--sync auto``'s control flow with scripted estimates and real files: the keypoints shift cam_b by 2 and the
    silhouettes put it at 2.87, so their mean (2.535) asks for 3. Its frames are renumbered by 3 (the file of source
    frame 0 becomes frame 3), everything is estimated again, and the entry counts from the recording: applied 3,
    offset 3 + 0.1, whole 3, the keypoints' and the silhouettes' own figures shifted by 3 too. When the second
    estimates disagree, the files go back and the first estimates stand: the keypoints' shift of 2 is made."""
    first = {"cam_a": combined(_entry(0.1, 0, -0.1)), "cam_b": combined(_entry(2.2, 2, 2.87, status="out of step"))}
    first["cam_b"]["confidence"] = "high"
    again = {"cam_a": combined(_entry(0.1, 0, -0.1)), "cam_b": combined(_entry(-0.1, 0, 0.3))}
    seen = _files(tmp_path / "made", ["cam_a", "cam_b"])
    _scripted(monkeypatch, first, again)
    out = sync_apply.synchronise(seen, tmp_path / "made", "auto")
    entry = out.sync["cameras"]["cam_b"]
    assert (entry["applied_frames"], entry["whole_frames"], entry["offset_frames"]) == (3, 3, 3.1)
    assert entry["keypoints"]["offset_frames"] == 2.9 and entry["silhouettes"]["offset_frames"] == 3.3
    assert entry["status"] == "out of step" and entry["confidence"] == "high" and out.sync["mode"] == "auto"
    assert out.frames[1] == list(range(3, 11)) and out.sync["cameras"]["cam_a"]["applied_frames"] == 0
    for sub, suffix in (("cam_b", "jpg"), ("mask_raw/cam_b", "png")):
        assert (tmp_path / "made" / sub / f"{3:06d}.{suffix}").read_text() == "cam_b 0"
    disagree = dict(again, cam_b=dict(again["cam_b"], status="uncertain"))
    seen = _files(tmp_path / "undone", ["cam_a", "cam_b"])
    _scripted(monkeypatch, first, disagree)
    out = sync_apply.synchronise(seen, tmp_path / "undone", "auto")
    assert (
        out.frames[1] == list(range(2, 10)) and (tmp_path / "undone" / "cam_b" / "000002.jpg").read_text() == "cam_b 0"
    )
    assert out.sync["cameras"]["cam_b"]["offset_frames"] == 2.54 and out.sync["cameras"]["cam_b"]["applied_frames"] == 2


def test_a_late_camera_is_found_on_a_timeline_of_every_second_frame(tmp_path):
    """``--stride 2``: the timeline holds frames 0, 2, 4, ... and only those have masks; camera 3 runs 4 frames (2
    steps) late. Offsets count steps: the silhouettes find it 2 steps late and the others in step. (Checked against
    offsets subtracted from frame numbers as they were: every camera came back empty.)"""
    cameras = _rig()
    _write_masks(tmp_path, cameras, late={2: 4}, turned={})
    for path in tmp_path.glob("*/*.png"):
        if int(path.stem) % 2:
            path.unlink()  # the prepare reads every second frame only
    timeline = list(range(0, N_FRAMES, 2))
    found = silhouette_offsets(cameras, timeline, tmp_path, _centres()[::2], [0] * len(cameras), stride=2)
    assert found["cam3"]["whole_frames"] == 2 and abs(found["cam3"]["offset_frames"] - 2) < 0.4  # as above
    for name in ("cam1", "cam2", "cam4"):
        assert found[name]["whole_frames"] == 0 and abs(found[name]["offset_frames"]) < 0.4
