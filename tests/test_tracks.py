"""Linking people into tracks (pipelines.prepare.people): a new track joins an ended one only within that one's
reach, however near another ended track is."""

import numpy as np

from pipelines.prepare.people import JOIN_RADIUS, TRACK_RADIUS, Track, link_tracks


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
