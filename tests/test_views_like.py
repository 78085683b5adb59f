"""A capture seen as another rig sees its person (pipelines.synthetic.views_like): the rig's geometry against
hand-built cameras, and the written capture's splits."""

import json
import shutil

import numpy as np
import pytest

from pipelines.datasets.capture import ZjuCapture
from pipelines.synthetic.views_like import axes_meeting_point, matching_views, rig_azimuths, views_like


def _looking_at(centre, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """cam_from_world (4, 4) of an OpenCV camera (x right, y down, z forward) at ``centre`` aimed at ``target``."""
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    rotation = np.stack([x, np.cross(z, x), z])
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, -rotation @ centre
    return pose


def _ring(azimuths_deg, target=(0.4, -0.2, 1.0), radius=3.0, heights=(1.8, 2.1, 1.5, 2.0)):
    angles = np.radians(azimuths_deg)
    centres = [
        np.array([target[0] + radius * np.cos(a), target[1] + radius * np.sin(a), h]) for a, h in zip(angles, heights)
    ]
    return np.stack([_looking_at(c, target) for c in centres])


def test_the_axes_meet_at_the_target_and_the_azimuths_are_the_rigs():
    """Cameras at azimuths 10, 100, 215, 300 degrees (different heights) aimed at one point: the least-squares meeting
    point is that point and the azimuths are recovered relative to the first camera. float64, a 3 x 3 solve of
    well-conditioned sums: 1e-9."""
    rig = _ring([10, 100, 215, 300])
    rotations = rig[:, :3, :3]
    centres = -np.einsum("cji,cj->ci", rotations, rig[:, :3, 3])
    assert np.allclose(axes_meeting_point(centres, rotations[:, 2]), [0.4, -0.2, 1.0], atol=1e-9)
    # given the vertical, exact (float64 trigonometry: 1e-9 degrees)
    assert np.allclose(rig_azimuths(rig, np.array([0.0, 0.0, 2.0])), [0, 90, -155, -70], atol=1e-9)
    # from the centres alone (heights 1.5-2.1 m at 3 m: the plane through them tilts by a few degrees), to 2 degrees
    assert np.allclose(rig_azimuths(rig), [0, 90, -155, -70], atol=2.0)
    level = _ring([10, 100, 215, 300], heights=(1.8, 1.8, 1.8, 1.8))  # a level ring: the plane's normal is exact
    assert np.allclose(rig_azimuths(level), [0, 90, -155, -70], atol=1e-9)


def test_matching_views_take_the_nearest_free_camera():
    """Rig A holds out camera 3 (at 300 degrees) and trains 0, 1, 2 (10, 100, 215); rig B, 12 cameras every 30
    degrees, holds out camera 0: the wanted offsets -290, -200, -85 degrees (70, 160, 275 from camera 0) fall
    nearest cameras 2, 5 and 9."""
    like = np.array([10.0, 100.0, 215.0, 300.0])
    ring = np.arange(12) * 30.0
    assert matching_views(like, [0, 1, 2], 3, ring, 0) == [2, 5, 9]


def test_a_capture_like_itself_keeps_its_views(data_root_64, tmp_path):
    """The 64-px synthetic capture made like a copy of itself that trains on cameras 1-3 and holds out 0: the same
    training cameras, 70 % of the frames, and a capture the loaders read."""
    source = data_root_64 / "synthetic" / "taichi"
    like = tmp_path / "like"
    shutil.copytree(source, like)
    splits = {"train_frames": list(range(7)), "novel_frames": [7, 8, 9], "train_views": [1, 2, 3], "test_views": [0]}
    (like / "splits.json").write_text(json.dumps(splits))
    written = views_like(source, like, tmp_path / "out")
    assert written["train_views"] == [1, 2, 3] and written["test_views"] == [0]
    assert written["train_frames"] == list(range(7)) and written["novel_frames"] == [7, 8, 9]
    protocol = ZjuCapture(tmp_path / "out").protocol("narf")
    assert list(protocol.train_views) == [1, 2, 3] and list(protocol.test_views) == [0]
    with pytest.raises(FileExistsError):  # a folder holding something else is never overwritten
        views_like(source, like, like)


def test_a_source_that_is_no_capture_is_one_line_and_exit_2(tmp_path, capsys):
    from pipelines.synthetic.views_like import main

    assert main([str(tmp_path / "none"), str(tmp_path / "like"), str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no annots.npy" in err[0]
