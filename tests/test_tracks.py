"""Linking people into tracks (pipelines.prepare.people): a new track joins an ended one only within that one's
reach, however near another ended track is; nobody found, somebody entering mid-take, ties, and the largest person's
size counted only in front of each camera."""

import numpy as np
import pytest

from pipelines.prepare.people import (
    JOIN_RADIUS,
    MAX_GAP,
    TRACK_RADIUS,
    Track,
    _image_height,
    link_tracks,
    nearest_track,
)
from pipelines.prepare.run import _others


def _at(x: float) -> np.ndarray:
    """Two targets at (x, 0, 1): the person's centre is there."""
    return np.array([[x, 0.0, 1.0], [x, 0.0, 1.0]])


def test_a_new_track_joins_the_ended_track_within_reach_not_the_nearest():
    """A ended at frame 0 at x = 0; B (frames 5-11) at x = 1.5, too far from A to be A; at frame 12 somebody appears
    at x = 0.9: 0.6 m from B one frame after it ended (B's reach: 0.5 m) and 0.9 m from A twelve frames after (past
    the frames a track stays open, so the tracks are joined afterwards; A's reach: 1 m). They are A, not B."""
    assert TRACK_RADIUS == 0.5 and JOIN_RADIUS == 1.0  # the reaches the example is built on
    per_frame = {0: [(_at(0.0), 4)], **{f: [(_at(1.5), 4)] for f in range(5, 12)}, 12: [(_at(0.9), 4)]}
    tracks = link_tracks(per_frame)
    assert len(tracks) == 2
    a, b = sorted(tracks, key=lambda t: t.first)
    assert sorted(a.points) == [0, 12] and sorted(b.points) == list(range(5, 12))


def test_nobody_within_reach_starts_a_new_track():
    per_frame = {0: [(_at(0.0), 4)], 1: [(_at(0.7), 4)]}  # 0.7 m in one frame: somebody else
    assert [sorted(t.points) for t in link_tracks(per_frame)] == [[0], [1]]
    assert isinstance(link_tracks({0: [(_at(0.0), 4)]})[0], Track)


def _camera(name="cam"):
    """A 100 px camera at the origin looking along +z, focal 100 px: a 1 m tall body 2 m away spans 50 rows."""
    from pipelines.datasets.camera import Camera

    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    return Camera(name, K, np.zeros(5), np.eye(4), 100, 100)


def test_the_largest_person_counts_the_points_in_front_of_the_camera():
    """_image_height by hand: a body from y = -0.5 to 0.5 m at z = 2 m spans 50 of 100 rows (0.5); a stray target
    behind the camera (z = -0.1 m), which projects 500 rows off, adds nothing."""
    body = np.array([[0.0, -0.5, 2.0], [0.0, 0.5, 2.0]])
    stray = np.array([[0.0, 0.05, -0.1]])
    track = Track({0: body, 1: np.vstack([body, stray])})
    assert _image_height(track, [_camera()]) == pytest.approx(0.5)  # pinhole projection, exact up to rounding
    assert _image_height(Track({0: stray}), [_camera()]) == 0.0  # seen by no camera


def test_nobody_found_is_said_in_words():
    """No people in any frame: no tracks, and choosing among none is a ValueError that says so."""
    assert link_tracks({}) == [] and link_tracks({0: [], 1: []}) == []
    with pytest.raises(ValueError, match="nobody was followed"):
        nearest_track([], {0: np.zeros((2, 3))})


def test_a_person_entering_mid_take_is_a_track_of_their_own():
    """A stands at x = 0 throughout; B enters at frame 10 two metres away: two tracks, B's from frame 10."""
    per_frame = {f: [(_at(0.0), 4)] + ([(_at(2.0), 3)] if f >= 10 else []) for f in range(20)}
    a, b = sorted(link_tracks(per_frame), key=lambda t: t.first)
    assert sorted(a.points) == list(range(20)) and sorted(b.points) == list(range(10, 20))


def test_equal_distances_choose_the_first_track():
    """Two tracks equally near the route (both within reach in every frame, the same median distance): the first
    is chosen, so the choice does not depend on anything but the order the tracks were found in."""
    route = {f: _at(0.0) for f in range(5)}
    left, right = Track({f: _at(-0.1) for f in range(5)}), Track({f: _at(0.1) for f in range(5)})
    assert nearest_track([left, right], route) == 0 and nearest_track([right, left], route) == 0


def test_the_other_people_fill_short_gaps_and_stop_at_their_ends():
    # the detector finds one person a view, so somebody beside the followed person drops out of a frame or two: the
    # others are drawn where interpolated within MAX_GAP (frame 3: halfway between 1 m and 2 m), never held past
    # their ends
    followed = Track({f: np.zeros((2, 3)) for f in range(20)})
    other = Track({2: np.ones((2, 3)), 4: 2 * np.ones((2, 3)), 6 + MAX_GAP + 1: np.ones((2, 3))})
    others = _others([followed, other], 0, list(range(20)))
    assert np.allclose(others[3][0], 1.5) and len(others[2]) == 1
    assert others[5] == [] and others[6 + MAX_GAP] == []  # a gap wider than MAX_GAP stays open
    assert others[1] == [] and others[19] == []  # before the first and after the last frame: nobody
