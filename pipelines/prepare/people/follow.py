"""The people stage of a prepare: whom the capture follows, triangulated in every frame
(docs/guides/real-captures.md, *Other people in view*). The tracks come from :mod:`pipelines.prepare.people.targets`,
the choice from :mod:`pipelines.prepare.people.tracks`, the second looks from :mod:`pipelines.prepare.people.crops`
and the views left out where people overlap from :mod:`pipelines.prepare.people.occlusion`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipelines.datasets.errors import CaptureError
from pipelines.prepare.people.targets import find_tracks, triangulate_people
from pipelines.prepare.people.tracks import choose_track, guide
from pipelines.prepare.request import PrepareRequest

#: with several people and ``--person best-seen``, each is looked for in every view of one frame in this many
#: before the choice (docs/guides/real-captures.md, *Other people in view*)
CHOICE_STRIDE = 10


def common_frames(seen, request: PrepareRequest) -> list[int]:
    """The source frames every camera has (after the cameras were put in step); an error naming the recording when
    there is none."""
    common = sorted(set.intersection(*(set(f) for f in seen.frames)))
    if not common:
        raise CaptureError(f"{request.recording}: the cameras share no frame in {request.start}:{request.stop or ''}")
    return common


def follow_person(folder: Path, seen, detector, request: PrepareRequest):
    """The person ``request.follow`` picks, triangulated in the frames every camera has (:func:`common_frames`;
    ``pipelines.prepare.people.tracks``). With a
    ``detector`` and keypoints from it, views that missed a person are detected again around them
    (:func:`_look_again`); with keypoints from files and masks from the detector's segmenter, views whose mask came
    with somebody else's detection are (``redetect_masks``). Views where other people overlap the person are left
    out (``pipelines.prepare.people.occlusion``). Every used view's mask is the person's (their crop's, or
    the whole image's when its detection is theirs; a view with only somebody else's is no longer used), cut to them.
    ``seen.people`` gains the crops' detections (keypoints from the detector) and ``seen.person`` says whom."""
    from pipelines.prepare.people.crops import crop_masks, cut_masks, redetect_masks
    from pipelines.prepare.people.occlusion import leave_out_overlapped

    frames = common_frames(seen, request)
    tracks = find_tracks(seen.cameras, seen.people, frames, request.threshold)
    if not tracks:
        raise CaptureError(
            f"{request.recording}: no person is seen by two agreeing views in any of the {len(frames)} frames read"
        )
    detector = detector if len(seen.cameras) > 2 else None  # two views: a crop can add no third opinion
    files = request.keypoints is not None
    tracks, unseen = _seen_in_masks(folder, seen, tracks, frames) if files else (tracks, 0)
    # the detector's one person per view, whose mask the view holds until a crop of the followed person replaces it
    if files:
        whole = {(v, f): o for v, by_frame in enumerate(seen.mask_owners) for f, o in by_frame.items() if o[:, 2].any()}
    else:
        whole = {(v, f): found[0] for v, by_frame in enumerate(seen.people) for f, found in by_frame.items() if found}
    tracks, chosen, whom, crops, looked = _look_again(
        folder, seen, frames, tracks, None if files else detector, request
    )
    route, others = guide(tracks[chosen], frames), _others(tracks, chosen, frames)
    found = triangulate_people(seen.cameras, seen.people, frames, request.threshold, route, others)
    if not found.frames:
        raise CaptureError(f"{request.recording}: the person followed is never seen by two agreeing views")
    overlapped = leave_out_overlapped(seen.cameras, found)
    if files and detector is not None:  # a detector with keypoint files: the masks are the segmenter's
        total = len(seen.cameras) * len(found.frames)
        with tqdm(total=total, desc="looking at the masks", unit="view", disable=not request.progress) as bar:
            looked = redetect_masks(folder, seen, found, crops, detector, request.threshold, others, bar.update)
    without_mask = crop_masks(folder, seen, found, crops, whole if detector else {}, detector, request.threshold)
    cut_masks(folder, seen.cameras, found)
    seen.person = {
        "choice": request.follow if isinstance(request.follow, str) else ":".join(map(str, request.follow)),
        "followed": whom,
        "people_seen": len(tracks),
        "people_without_mask": unseen,
        "frames_per_person": sorted((len(t.points) for t in tracks), reverse=True),
        "frames_sides_turned": sorted(tracks[chosen].turned),
        "views_detected_again": looked,
        "views_without_their_mask": without_mask,
        "views_overlapped_by_others": sum(overlapped),
    }
    return found


def _seen_in_masks(folder: Path, seen, tracks, frames: list[int]):
    """The tracks of keypoint files that the views' masks show (``pipelines.prepare.people.tracks.mask_support`` at
    least ``MASK_SUPPORT``, on one frame of ``CHOICE_STRIDE``), and how many were dropped; all of them when none is
    shown (the masks then say nothing of whom to follow)."""
    import cv2

    from pipelines.prepare.people.tracks import MASK_SUPPORT, mask_support

    def read_mask(v: int, frame: int):
        image = cv2.imread(str(folder / "mask_raw" / seen.cameras[v].name / f"{frame:06d}.png"), cv2.IMREAD_GRAYSCALE)
        return None if image is None else image > 0

    if len(tracks) < 2:
        return tracks, 0
    support = [mask_support(t, seen.cameras, read_mask, frames[::CHOICE_STRIDE]) for t in tracks]
    shown = [t for t, share in zip(tracks, support) if not share < MASK_SUPPORT]  # NaN: nothing to judge by
    return (shown, len(tracks) - len(shown)) if shown else (tracks, 0)


def _look_again(folder: Path, seen, frames: list[int], tracks, detector, request: PrepareRequest):
    """Choose the track (``choose_track``) and, with a ``detector``, look for people in the views that missed them
    (``pipelines.prepare.people.crops.redetect``): for ``best-seen`` with several people, each of them in one frame of
    ``CHOICE_STRIDE`` before the choice; then the chosen one in every frame. Returns the tracks found again, the
    chosen one's index, the line saying whom, the crops and the number of views detected again."""
    from pipelines.prepare.people.crops import redetect
    from pipelines.prepare.people.tracks import nearest_track

    crops, looked, counted = {}, 0, None
    several = detector is not None and len(tracks) > 1 and request.follow == "best-seen"
    total = len(seen.cameras) * (len(frames) + several * len(tracks) * len(frames[::CHOICE_STRIDE]))
    with tqdm(
        total=total, desc="looking for the person", unit="view", disable=not request.progress or not detector
    ) as bar:
        if several:
            counted = frames[::CHOICE_STRIDE]
            for k, track in enumerate(tracks):
                rest = _others(tracks, k, counted)
                looked += redetect(
                    folder, seen, guide(track, counted), crops, detector, request.threshold, rest, bar.update
                )
            tracks = find_tracks(seen.cameras, seen.people, frames, request.threshold)
        chosen, whom = choose_track(tracks, request.follow, seen.cameras, counted)
        if detector is not None:
            route, rest = guide(tracks[chosen], frames), _others(tracks, chosen, frames)
            added = redetect(folder, seen, route, crops, detector, request.threshold, rest, bar.update)
            if added:
                looked += added
                tracks = find_tracks(seen.cameras, seen.people, frames, request.threshold)
                if not tracks:
                    raise ValueError(f"{folder}: after a second look nobody is seen by two cameras at once")
                chosen = nearest_track(tracks, route)
    return tracks, chosen, whom, crops, looked


def _others(tracks, chosen: int, frames) -> dict[int, list[np.ndarray]]:
    """By frame, the targets of every track but ``chosen``: their own, or interpolated across a gap of up to
    ``MAX_GAP`` frames (``guide`` without holding them past their ends), since the detector finds one person a view
    and somebody beside the followed person is often missed in a frame or two."""
    guided = [guide(t, frames, hold=0) for k, t in enumerate(tracks) if k != chosen]
    return {f: [g[f] for g in guided if f in g] for f in frames}
