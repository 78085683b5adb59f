"""Whom a capture follows when several people are in view (docs/guides/real-captures.md, *Other people in view*).

Every person that at least two views agree on is triangulated in every frame (``consensus`` again and again on the
detections left over), and the people are linked from frame to frame into tracks: a track goes on while its person
moves at most ``TRACK_RADIUS`` a frame (at most ``JOIN_RADIUS`` over any gap), over gaps of at most ``MAX_GAP``
frames; tracks that follow one another in time, the second starting within that reach of where the first ended, are
one person, and so are tracks whose centres agree in every frame both have. ``--person`` then picks one track: the one
seen best (most agreeing views over the recording), the largest in the images, or the one nearest a point of the
world or a pixel of a camera.

A person and their left/right mirror reproject alike in every view (a detector's labels swapped), so each frame's
consensus may find either; a track's sides are made to hold from frame to frame (:func:`orient_sides`) before it
guides the triangulation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipelines.datasets.camera import Camera, project_distorted
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.keypoints import TARGETS, mirror_index
from pipelines.prepare.people.multiview import consensus, project, triangulate_robust

#: metres a followed person may move per frame (a sprinter at 60 fps moves 0.2 m); beyond it, it is somebody else
TRACK_RADIUS = 0.5
#: frames a track may miss and still go on; past them, tracks are joined only by ``JOIN_RADIUS``
MAX_GAP = 10
#: frames before a track's first and after its last in which the person is still looked for where last seen
HOLD = 5
#: the most metres a person may move between two frames in which they are seen (however many frames apart)
JOIN_RADIUS = 1.0
#: two people found in one frame whose centres (the median of their targets) are nearer than this (metres) are one
#: person that the views saw in two inconsistent ways, mirrored for instance (bodies cannot be nearer)
SAME_PERSON = 0.3
#: the choices of ``--person`` besides a point or a pixel
CHOICES = ("best-seen", "largest")
#: a frame keeps the sides of the frame before it when one of its two orientations (as found, or mirrored left for
#: right) lies at most this fraction of the other's distance from it; else the sides are undecided there and a new
#: stretch of frames begins (:func:`orient_sides`)
SIDE_RATIO = 0.5


@dataclass
class Track:
    """One person over the frames: ``points[frame]`` (T, 3) triangulated targets, ``views[frame]`` agreeing views,
    ``sides[frame]`` the agreeing views whose detection was taken as labelled minus those taken mirrored (absent: 0),
    ``turned`` the frames whose targets :func:`orient_sides` mirrored from what their consensus found."""

    points: dict[int, np.ndarray] = field(default_factory=dict)
    views: dict[int, int] = field(default_factory=dict)
    sides: dict[int, int] = field(default_factory=dict)
    turned: set[int] = field(default_factory=set)

    @property
    def first(self) -> int:
        return min(self.points)

    @property
    def last(self) -> int:
        return max(self.points)

    def centre(self, frame: int) -> np.ndarray:
        """(3,) the median of the frame's triangulated targets."""
        return np.nanmedian(self.points[frame], axis=0)


def parse_person(text: str):
    """``--person``'s value: ``best-seen``, ``largest``, ``near:X,Y,Z`` (metres, the calibration's world) or
    ``pixel:CAM:U,V`` (a pixel of camera CAM's frames); raises ValueError with what is accepted."""
    if text in CHOICES:
        return text
    kind, _, rest = text.partition(":")
    try:
        if kind == "near":
            point = tuple(float(v) for v in rest.split(","))
            if len(point) == 3 and np.isfinite(point).all():
                return ("near", point)
        if kind == "pixel":
            camera, _, uv = rest.rpartition(":")
            pixel = tuple(float(v) for v in uv.split(","))
            if camera and len(pixel) == 2 and np.isfinite(pixel).all():
                return ("pixel", camera, pixel)
    except ValueError:
        pass
    raise ValueError(f"{text!r}: expected best-seen, largest, near:X,Y,Z (metres) or pixel:CAM:U,V")


def people_in_frame(P, undistorted, heights, threshold) -> list[tuple[np.ndarray, list[int]]]:
    """Every person two or more views agree on in one frame: (targets (T, 3), the detection each view gave it).

    Args:
        P: (V, 3, 4). undistorted: per view, its detections and then their mirrors (``_with_mirrored``); a view's
            detection and its mirror are taken together. heights: (V,). threshold: as ``consensus``'s.
    """
    left = [list(range(len(found))) for found in undistorted]  # indices still free in each view
    blank = next((np.zeros_like(d) for found in undistorted for d in found), None)
    found_people = []
    while True:
        pool = [[undistorted[v][i] for i in left[v]] for v in range(len(undistorted))]
        choice = consensus(P, pool, heights, threshold)
        person = [left[v][p] if p >= 0 else -1 for v, p in enumerate(choice.person)]
        if sum(p >= 0 for p in person) < 2:
            return found_people
        xy = np.stack([undistorted[v][p] if p >= 0 else blank for v, p in enumerate(person)])
        xyz, _ = triangulate_robust(P, xy[..., :2].transpose(1, 0, 2), xy[..., 2].T, heights, threshold)
        if np.isfinite(xyz).all(-1).sum() < 3:
            return found_people  # a consensus that cannot be triangulated: no further person either
        if all(_centre_distance(xyz, other) > SAME_PERSON for other, _ in found_people):
            found_people.append((xyz, person))
        for v, p in enumerate(person):
            if p >= 0:
                half = len(undistorted[v]) // 2
                left[v] = [i for i in left[v] if i % half != p % half]


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    """Median over the targets both have of the distance between two (T, 3) people (inf: none shared)."""
    d = np.linalg.norm(a - b, axis=-1)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if d.size else np.inf


def reach(gap: int) -> float:
    """Metres a person's centre may move in ``gap`` frames: ``TRACK_RADIUS`` a frame, at most ``JOIN_RADIUS``."""
    return min(TRACK_RADIUS * gap, JOIN_RADIUS)


def _centre_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Distance between the centres (median of the targets) of two (T, 3) people: a left/right mirror has the same."""
    return float(np.linalg.norm(np.nanmedian(a, axis=0) - np.nanmedian(b, axis=0)))


def link_tracks(per_frame: dict[int, list[tuple]]) -> list[Track]:
    """Tracks from each frame's people (``per_frame[frame]``: (targets, agreeing views) or (targets, agreeing views,
    side votes as ``Track.sides``)), frames in order: each person joins the open track whose centre is nearest,
    within :func:`reach` of the frames since it was last seen (nearest pairs first), else starts one; then tracks
    that follow one another are joined (module docstring)."""
    tracks: list[Track] = []
    for frame in sorted(per_frame):
        people = per_frame[frame]
        open_tracks = [t for t in tracks if 0 < frame - t.last <= MAX_GAP]
        pairs = sorted(
            (_centre_distance(person[0], t.points[t.last]), i, k)
            for i, person in enumerate(people)
            for k, t in enumerate(open_tracks)
        )
        taken_people, taken_tracks = set(), set()
        for distance, i, k in pairs:
            track = open_tracks[k]
            if i in taken_people or k in taken_tracks or distance > reach(frame - track.last):
                continue
            _add(track, frame, *people[i])
            taken_people.add(i)
            taken_tracks.add(k)
        for i, person in enumerate(people):
            if i not in taken_people:
                tracks.append(_add(Track(), frame, *person))
    return _joined(tracks)


def _add(track: Track, frame: int, points: np.ndarray, views: int, sides: int = 0) -> Track:
    track.points[frame], track.views[frame], track.sides[frame] = points, views, sides
    return track


def orient_sides(track: Track) -> Track:
    """The track with each frame's targets as found or mirrored left for right, so that its sides hold over time.

    A person and their mirror reproject alike, so a frame's consensus may find either. Each frame takes the
    orientation nearer the frame before it (median distance over the targets) when that one lies at most
    ``SIDE_RATIO`` of the other's distance; else (a gap, a person standing in a mirror-symmetric pose) a new stretch
    begins. Each stretch then takes, as a whole, the orientation most of its views' detections give
    (``Track.sides`` summed): the detectors' labels decide which side is left, continuity which frames they
    swapped. Returns a new Track (``sides`` as oriented, ``turned`` the frames mirrored); ``views`` are shared.
    """
    order = [mirror_index(t) for t in range(len(TARGETS))]
    frames = sorted(track.points)
    points, sides, turned = dict(track.points), dict(track.sides), set()

    def turn(frame: int) -> None:
        points[frame], sides[frame] = points[frame][order], -sides.get(frame, 0)
        turned.symmetric_difference_update({frame})

    stretches: list[list[int]] = []
    for i, frame in enumerate(frames):
        if i:
            before = points[frames[i - 1]]
            as_found, mirrored = _distance(points[frame], before), _distance(points[frame][order], before)
            if np.isfinite(max(as_found, mirrored)) and min(as_found, mirrored) <= SIDE_RATIO * max(as_found, mirrored):
                if mirrored < as_found:
                    turn(frame)
                stretches[-1].append(frame)
                continue
        stretches.append([frame])
    for stretch in stretches:
        if sum(sides.get(f, 0) for f in stretch) < 0:
            for frame in stretch:
                turn(frame)
    return Track(points, track.views, sides, turned)


def _joined(tracks: list[Track]) -> list[Track]:
    """Tracks merged: a later one that starts within :func:`reach` of where an earlier one ended (the nearest of
    those within their reach), or whose frames shared with an earlier one all have their centres within
    ``SAME_PERSON``."""
    out: list[Track] = []
    for track in sorted(tracks, key=lambda t: t.first):
        same = [t for t in out if _shares_person(t, track)]
        if same:
            for frame, points in track.points.items():
                if frame not in same[0].points:
                    _add(same[0], frame, points, track.views[frame], track.sides.get(frame, 0))
            continue
        # the candidates within their own reach: a nearer track out of its reach is somebody else
        candidates = [
            (distance, i)
            for i, t in enumerate(out)
            if t.last < track.first
            and (distance := _centre_distance(t.points[t.last], track.points[track.first]))
            <= reach(track.first - t.last)
        ]
        if candidates:
            earlier = out[min(candidates)[1]]
            earlier.points.update(track.points)
            earlier.views.update(track.views)
            earlier.sides.update(track.sides)
        else:
            out.append(track)
    return out


def _shares_person(a: Track, b: Track) -> bool:
    """Whether two tracks that overlap in time follow one person: their centres within ``SAME_PERSON`` in every
    shared frame."""
    shared = set(a.points) & set(b.points)
    return bool(shared) and all(_centre_distance(a.points[f], b.points[f]) <= SAME_PERSON for f in shared)


def choose_track(tracks: list[Track], how, cameras: list[Camera], frames=None) -> tuple[int, str]:
    """The index of the track ``how`` (:func:`parse_person`) picks, and a line saying whom (for the report);
    ``best-seen`` counts the agreeing views in ``frames`` (None: all)."""
    if not tracks:
        raise CaptureError(
            "no person to follow: no one is seen by two or more cameras that agree in any frame (check the keypoints, "
            "the calibration and that the cameras are in step)"
        )
    if how == "best-seen" or len(tracks) == 1:
        counted = set(frames) if frames is not None else None
        scores = [sum(n for f, n in t.views.items() if counted is None or f in counted) for t in tracks]
        best = int(np.argmax(scores))
        among = f" in {len(counted)} frames looked at in every view" if counted is not None else ""
        return best, f"the person seen best ({scores[best]} agreeing views{among})"
    if how == "largest":
        sizes = [_image_height(t, cameras) for t in tracks]
        best = int(np.argmax(sizes))
        return best, f"the largest person (median {100 * sizes[best]:.0f} % of the image height)"
    if how[0] == "near":
        point = np.array(how[1])
        distances = [float(np.median([np.linalg.norm(t.centre(f) - point) for f in t.points])) for t in tracks]
        best = int(np.argmin(distances))
        return best, f"the person nearest {tuple(how[1])} (median {distances[best]:.2f} m)"
    names = [c.name for c in cameras]
    if how[1] not in names:
        raise CaptureError(f"--person pixel:{how[1]}:...: {how[1]} is not one of the cameras {names}")
    camera = cameras[names.index(how[1])]
    distances = [_pixel_distance(t, camera, np.array(how[2])) for t in tracks]
    best = int(np.argmin(distances))
    return best, f"the person nearest pixel {tuple(how[2])} of {how[1]} when first seen ({distances[best]:.0f} px)"


#: the share of a person's projected targets that the views' masks must cover for them to be somebody in the videos
MASK_SUPPORT = 0.5


def mask_support(track: Track, cameras: list[Camera], read_mask, frames: list[int]) -> float:
    """The share of ``track``'s targets in ``frames`` that land on a person in the views' masks: each finite target
    in front of a camera and inside its image, projected, counts once a view; ``read_mask(v, frame)`` gives view v's
    (H, W) bool mask or None. Keypoint files can hold people the videos do not show (a detector's false person, a
    take's other version): their targets land on the background. NaN where nothing could be looked at."""
    inside = total = 0
    for frame in (f for f in frames if f in track.points):
        finite = track.points[frame][np.isfinite(track.points[frame]).all(-1)]
        for v, camera in enumerate(cameras):
            mask = read_mask(v, frame)
            depth = finite @ camera.cam_from_world[2, :3] + camera.cam_from_world[2, 3]
            if mask is None or not (depth > 0).any():
                continue
            pixels = np.round(project_distorted(camera, finite[depth > 0])).astype(int)
            seen = (pixels >= 0).all(-1) & (pixels < [mask.shape[1], mask.shape[0]]).all(-1)
            inside += int(mask[pixels[seen, 1], pixels[seen, 0]].sum())
            total += int(seen.sum())
    return inside / total if total else float("nan")


def _image_height(track: Track, cameras: list[Camera]) -> float:
    """Median over frames and cameras of the track's projected extent (rows), as a fraction of the image height. Only
    the points in front of a camera count (a point behind it projects through the centre, upside down); a camera
    that sees fewer than two of a frame's points adds nothing for that frame (0 where no camera sees any)."""
    sizes = []
    for points in track.points.values():
        finite = points[np.isfinite(points).all(-1)]
        for camera in cameras:
            depth = finite @ camera.cam_from_world[2, :3] + camera.cam_from_world[2, 3]
            in_front = finite[depth > 0]
            if len(in_front) < 2:
                continue
            rows = project_distorted(camera, in_front)[:, 1]
            sizes.append((rows.max() - rows.min()) / camera.height)
    return float(np.median(sizes)) if sizes else 0.0


def _pixel_distance(track: Track, camera: Camera, pixel: np.ndarray, frames: int = 5) -> float:
    """Median distance (pixels) between ``pixel`` and the track's projected centre over its first ``frames``."""
    first = sorted(track.points)[:frames]
    centres = np.stack([track.centre(f) for f in first])
    return float(np.median(np.linalg.norm(project_distorted(camera, centres) - pixel, axis=-1)))


def guide(track: Track, frames: list[int], hold: int = HOLD) -> dict[int, np.ndarray]:
    """The track's targets at each of ``frames``: its own where it has them, else interpolated linearly between
    its frames on either side when both are within ``MAX_GAP``, or held from its first or last frame for up to
    ``hold`` frames beyond it (where the crops may find the person again); frames farther from the track have none."""
    known = sorted(track.points)
    out = {}
    for frame in frames:
        at = np.searchsorted(known, frame)
        if frame in track.points:
            out[frame] = track.points[frame]
        elif 0 < at < len(known) and known[at] - known[at - 1] <= MAX_GAP:
            before, after = known[at - 1], known[at]
            w = (frame - before) / (after - before)
            out[frame] = (1 - w) * track.points[before] + w * track.points[after]
        elif at == 0 and known[0] - frame <= hold:
            out[frame] = track.points[known[0]]
        elif at == len(known) and frame - known[-1] <= hold:
            out[frame] = track.points[known[-1]]
    return out


def matches(P_v: np.ndarray, detection: np.ndarray, points: np.ndarray, height: float, threshold: float) -> bool:
    """Whether one view's detection (T, 3 undistorted) shows the person ``points`` (T, 3): the median reprojection
    error over the targets both have is within ``threshold`` of the height."""
    seen = (detection[:, 2] > 0) & np.isfinite(points).all(-1)
    if seen.sum() < 3:
        return False
    error = np.linalg.norm(project(P_v[None], points[seen])[:, 0] - detection[seen, :2], axis=-1)
    return bool(np.median(error) / height <= threshold)


def nearest_track(tracks: list[Track], route: dict[int, np.ndarray]) -> int:
    """The track that stays nearest ``route`` (targets by frame): the most frames within ``TRACK_RADIUS`` of it, then
    the smallest median distance (the followed person found again after more views were detected).

    Raises:
        ValueError: ``tracks`` is empty.
    """
    if not tracks:
        raise ValueError("no track to choose from: nobody was followed")
    keys = []
    for track in tracks:
        distances = [_distance(track.points[f], route[f]) for f in track.points if f in route]
        near = sum(d <= TRACK_RADIUS for d in distances)
        keys.append((-near, float(np.median(distances)) if distances else np.inf))
    return min(range(len(tracks)), key=keys.__getitem__)
