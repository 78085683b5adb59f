"""Linking people into tracks (pipelines.prepare.people.tracks): a new track joins an ended one only within that one's
reach, however near another ended track is; nobody found, somebody entering mid-take, ties, and the largest person's
size counted only in front of each camera; a track's left and right sides held over time."""

import numpy as np
import pytest

from pipelines.prepare.people.follow import _others
from pipelines.prepare.people.tracks import (
    JOIN_RADIUS,
    MAX_GAP,
    SIDE_RATIO,
    TRACK_RADIUS,
    Track,
    _image_height,
    link_tracks,
    nearest_track,
    orient_sides,
)


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


def _skeleton(x: float) -> np.ndarray:
    """(17, 3) targets of a person standing at (x, 0), facing -y: each left target 0.15 m to +x of its right one,
    heights by TARGET_NAMES' order (the head at 1.7 m), so a left/right mirror moves every side pair 0.3 m."""
    from pipelines.datasets.keypoints import TARGET_NAMES

    heights = {"pelvis": 1.0, "hip": 0.95, "knee": 0.5, "ankle": 0.1, "foot": 0.02, "neck": 1.5, "head": 1.7}
    heights.update({"shoulder": 1.45, "elbow": 1.15, "wrist": 0.9})
    points = []
    for name in TARGET_NAMES:
        side, _, part = name.partition("_") if name[1:2] == "_" else ("", "", name)
        points.append([x + {"l": 0.15, "r": -0.15, "": 0.0}[side], 0.0, heights[part]])
    return np.array(points)


def _mirror(points: np.ndarray) -> np.ndarray:
    from pipelines.datasets.keypoints import TARGETS, mirror_index

    return points[[mirror_index(t) for t in range(len(TARGETS))]]


def test_orient_sides_puts_back_frames_found_mirrored():
    """A person walking 1 cm a frame, found mirrored in frames 4 and 7 (most of those frames' views took their
    detections mirrored: votes -2 as found, +2 elsewhere). Each frame keeps the sides of the one before (0.01 m one
    way, 0.3 m the other), so the ten frames are one stretch, which its votes (+12 once oriented) leave as labelled."""
    truth = {f: _skeleton(0.01 * f) for f in range(10)}
    found = {f: _mirror(p) if f in (4, 7) else p for f, p in truth.items()}
    votes = {f: -2 if f in (4, 7) else 2 for f in truth}
    oriented = orient_sides(Track(found, {f: 4 for f in truth}, votes))
    for f in truth:
        np.testing.assert_array_equal(oriented.points[f], truth[f])
    assert oriented.sides == {f: 2 for f in truth} and oriented.views == {f: 4 for f in truth}
    assert oriented.turned == {4, 7}


def test_orient_sides_follows_the_detectors_labels_for_the_whole_stretch():
    """The same walk found mirrored throughout, with most views mirrored in every frame (votes -1): one stretch,
    turned as a whole. Frames 0-4 and 6-9 with a frame between where both orientations lie as far (no shared target
    with frame 4: the distance is infinite) are two stretches, each turned by its own votes."""
    truth = {f: _skeleton(0.01 * f) for f in range(10)}
    oriented = orient_sides(Track({f: _mirror(p) for f, p in truth.items()}, {}, {f: -1 for f in truth}))
    for f in truth:
        np.testing.assert_array_equal(oriented.points[f], truth[f])
    assert oriented.turned == set(truth)
    found = {f: _mirror(p) if f >= 5 else p for f, p in truth.items()}
    found[5] = np.full_like(truth[5], np.nan)  # nothing triangulated: the sides are undecided there
    votes = {f: 1 if f < 5 else -3 for f in truth}
    oriented = orient_sides(Track(found, {}, votes))
    for f in (*range(5), *range(6, 10)):
        np.testing.assert_array_equal(oriented.points[f], truth[f])
    assert oriented.turned == {5, 6, 7, 8, 9}  # frame 5 is a stretch of its own, turned by its own vote (-3)
    # the ratio that decides continuity: frames 0.01 m apart one way, 0.3 m the other, are well within it
    assert 0.01 <= SIDE_RATIO * 0.3


def test_tracks_keep_their_sides_where_most_views_swap_them():
    """find_tracks on four cameras around a person walking 1 cm a frame, one camera's detector labelling the sides
    swapped in every frame and, in frames 3 and 6, three of four: the person and their mirror reproject alike, so
    those frames' consensus may find either; the track's targets hold the true sides in every frame."""
    from pipelines.datasets.camera import Camera, project_distorted
    from pipelines.prepare.people.targets import find_tracks
    from pipelines.synthetic.scene import look_at

    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    cameras = [
        Camera(
            f"cam{i}",
            K,
            np.zeros(5),
            look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 1.2]), np.array([0, 0, 1.0])),
            640,
            480,
        )
        for i, a in enumerate(np.linspace(0.3, 0.3 + 1.5 * np.pi, 4))
    ]
    truth = {f: _skeleton(0.01 * f) for f in range(10)}
    people = [{} for _ in cameras]
    for f, points in truth.items():
        for v, camera in enumerate(cameras):
            swapped = v == 1 or (f in (3, 6) and v != 0)
            pixels = np.concatenate(
                [project_distorted(camera, _mirror(points) if swapped else points), np.ones((17, 1))], 1
            )
            people[v][f] = [pixels]
    (track,) = find_tracks(cameras, people, list(truth), threshold=0.02)
    for f, points in truth.items():
        # triangulated from exact pixels: the error is rounding (float64 DLT), far below the 0.3 m of a swap
        np.testing.assert_allclose(track.points[f], points, atol=1e-6)


def test_no_track_to_follow_is_a_capture_error_naming_the_cause():
    """No person seen by two agreeing cameras: one line a user can act on, not a bare ValueError. (Checked against
    the bare ``ValueError("no tracks")``: the test fails.)"""
    from pipelines.datasets.errors import CaptureError
    from pipelines.prepare.people.tracks import choose_track

    with pytest.raises(CaptureError, match="no person to follow"):
        choose_track([], "best-seen", [])
