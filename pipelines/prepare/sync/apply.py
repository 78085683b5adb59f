"""The cameras' time offsets applied to a capture (docs/guides/real-captures.md, *Cameras in step*): ``--sync``'s
modes, each camera's frames renumbered by its whole shift, and the record the report keeps. The estimates are
:mod:`pipelines.prepare.sync.keypoints`'s (the keypoints) and :mod:`pipelines.prepare.sync.silhouettes`'s (the masks).
Where the two looks agree within a frame, a camera's offset is their mean: on the Pose2Sim demo each is about a frame
off in one camera where the other is not (the keypoints in cam03, the silhouettes half a frame in cam04), and their mean
finds a camera cut by 2-5 frames either way within half a frame in 24 of 24 cuts where the keypoints alone did in 18
(docs/results/real-capture.md, *Cameras in step*). A camera whose mean calls for another whole shift than the
keypoints' is shifted by it and every offset estimated again (:func:`combined_shifts`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pipelines.datasets.errors import CaptureError
from pipelines.prepare.sync.keypoints import POSITION_AGREEMENT, find_offsets, triangulated_joints
from pipelines.prepare.sync.silhouettes import silhouette_offsets

#: with several people in this share of the views or more, ``auto`` reports and applies nothing before the person
#: is followed (each view's most confident detection may be somebody else)
CROWDED = 0.2


#: ``--sync`` words: estimate and apply, estimate and report only, neither
MODES = ("auto", "report", "off")
#: the fewest whole frames of a shift that the two looks' agreement makes of high confidence (:func:`combined`)
CONFIRMED = 2
#: the ``method`` of an offset that is the two looks' mean
METHOD_COMBINED = "the mean of the keypoints' estimate and the silhouettes'"


def parse_sync(text: str) -> str | dict[str, int]:
    """``--sync``: ``auto``, ``report``, ``off`` or ``CAM=OFFSET,...`` (whole frames, a camera's frame t showing the
    others' t + OFFSET); raises ValueError naming what is wrong."""
    if text in MODES:
        return text
    given = {}
    for item in text.split(","):
        name, _, value = item.partition("=")
        try:
            given[name.strip()] = int(value)
        except ValueError:
            raise ValueError(f"--sync: expected auto, report, off or CAM=FRAMES,..., got {item!r}") from None
        if not name.strip():
            raise ValueError(f"--sync: expected auto, report, off or CAM=FRAMES,..., got {item!r}")
    return given


def shift_camera(seen, folder, v: int, shift: int, stride: int):
    """Camera v's frames renumbered from source frame f to f + shift * stride: its observations and its files under
    ``folder`` (``<camera>/<frame>.jpg``, ``mask_raw/<camera>/<frame>.png``), moved in an order that never
    overwrites one not yet moved. Returns ``seen`` with the new numbering."""
    if shift == 0:
        return seen
    step = shift * stride
    name = seen.cameras[v].name
    order = sorted(seen.frames[v], reverse=step > 0)
    for frame in order:
        for sub, suffix in ((folder / name, "jpg"), (folder / "mask_raw" / name, "png")):
            (sub / f"{frame:06d}.{suffix}").replace(sub / f"{frame + step:06d}.{suffix}")
    frames = list(seen.frames)
    people = list(seen.people)
    frames[v] = [f + step for f in seen.frames[v]]
    people[v] = {f + step: found for f, found in seen.people[v].items()}
    owners = list(seen.mask_owners)
    if owners:
        owners[v] = {f + step: owner for f, owner in seen.mask_owners[v].items()}
    return replace(seen, frames=frames, people=people, mask_owners=owners)


def synchronise(seen, folder, sync: str | dict[str, int], stride: int = 1):
    """Estimate every camera's offset (unless ``sync`` is ``off``), apply whole frames, and return ``seen``
    renumbered with ``seen.sync`` its record. ``auto``: the shifts the two looks' mean asks for
    (:func:`combined_shifts`; everything then estimated again) and those :func:`find_offsets` asks for with high
    confidence; a dict: the user's, by camera name, then estimated again; ``report``: none. The record holds, per
    camera, :func:`find_offsets`' entry with ``offset_frames`` counted from the recording and ``applied_frames``
    (the frames shifted). With several people in ``CROWDED`` of the views or more, or estimates that do not explain
    every camera (:func:`_consistent`), ``auto`` reports instead (each view's most confident detection may be
    somebody else; :func:`report_followed` estimates again on the followed person)."""
    names = [c.name for c in seen.cameras]
    if isinstance(sync, dict):
        unknown = sorted(set(sync) - set(names))
        if unknown:
            raise CaptureError(f"--sync: {', '.join(unknown)} not among the cameras {names}")
    given = {n: (sync.get(n, 0) if isinstance(sync, dict) else 0) for n in names}
    seen = _shift_cameras(seen, folder, given, stride)
    if sync == "off":
        return replace(seen, sync={"mode": "off", "cameras": {n: {"applied_frames": 0} for n in names}})
    mode, note = (sync if isinstance(sync, str) else "given"), {}
    estimates, crowded = _estimate(seen, folder, stride)
    combined = combined_shifts(estimates) if mode == "auto" and crowded < CROWDED else {}
    if combined:  # made, and every offset estimated again; undone if the estimates then do not agree
        seen = _shift_cameras(seen, folder, combined, stride)
        again, _ = _estimate(seen, folder, stride)
        if _consistent(again):
            estimates = again
            given = {name: shift + combined.get(name, 0) for name, shift in given.items()}
        else:
            seen = _shift_cameras(seen, folder, {name: -shift for name, shift in combined.items()}, stride)
            combined = {}
    if mode == "auto" and crowded >= CROWDED:
        mode, note["note"] = "report", f"several people in {100 * crowded:.0f} % of the views: not applied"
    elif mode == "auto" and not _consistent(estimates):
        mode, note["note"] = "report", "the cameras' estimates do not agree (another person in view?): not applied"
    cameras = {}
    for v, name in enumerate(names):
        entry = dict(estimates[name])
        shift = entry.get("whole_frames", 0) if mode == "auto" and entry.get("confidence") == "high" else 0
        seen = shift_camera(seen, folder, v, shift, stride)
        for what in ("silhouettes", "keypoints", "speed_correlation"):  # counted from the recording, as the entry
            look = entry.get(what) or {}
            if look.get("offset_frames") is not None:
                entry[what] = dict(look, offset_frames=round(given[name] + look["offset_frames"], 2))
        entry["offset_frames"] = round(given[name] + entry["offset_frames"], 2)
        entry["whole_frames"] = given[name] + entry.get("whole_frames", 0)
        if combined.get(name):
            entry.update(status="out of step", confidence="high", shifted_by="keypoints and silhouettes")
        entry["applied_frames"] = given[name] + shift
        cameras[name] = entry
    return replace(seen, sync={"mode": mode, "cameras": cameras, **note})


def _shift_cameras(seen, folder, shifts: dict[str, int], stride: int):
    """``seen`` with each named camera's frames renumbered by its shift (:func:`shift_camera`)."""
    for v, camera in enumerate(seen.cameras):
        seen = shift_camera(seen, folder, v, shifts.get(camera.name, 0), stride)
    return seen


def _estimate(seen, folder, stride: int = 1) -> tuple[dict[str, dict], float]:
    """(every camera's estimate, :func:`~pipelines.prepare.sync.keypoints.find_offsets`' with the silhouettes' look and
    their mean where one person is in view and the raw masks are there; the share of views with several people), in
    steps of ``stride`` frames."""
    estimates = find_offsets(seen.cameras, seen.frames, seen.people)
    crowded = crowded_share(seen.people)
    if crowded < CROWDED and (folder / "mask_raw").is_dir():
        estimates = with_silhouettes(estimates, seen, folder / "mask_raw", stride)
    return estimates, crowded


def combined_shifts(estimates: dict[str, dict]) -> dict[str, int]:
    """The whole shifts (by camera name) that the two looks' mean asks for where it differs from the keypoints': a
    camera whose mean offset rounds to another whole number than its keypoints' shift, if the mean is a frame or more
    from step or the keypoints shifted it. A camera within a frame of step that the keypoints left alone stays: on
    the demo a camera cut by k spoils the others' triangulation, and the cameras not cut then read up to 0.65 frame
    off by both looks (docs/results/real-capture.md, *Cameras in step*)."""
    out = {}
    for name, entry in estimates.items():
        if entry.get("method") != METHOD_COMBINED:
            continue
        offset, whole = entry["offset_frames"], entry.get("whole_frames", 0)
        if int(round(offset)) != whole and (abs(offset) >= 1.0 or whole != 0):
            out[name] = int(round(offset))
    return out


def with_silhouettes(estimates: dict[str, dict], seen, folder, stride: int = 1) -> dict[str, dict]:
    """``estimates`` (:func:`~pipelines.prepare.sync.keypoints.find_offsets`) with each camera's ``silhouettes``: the
    offset the masks in ``folder`` (``<camera>/<source frame:06d>.png``) give near the keypoints' whole shifts
    (:func:`pipelines.prepare.sync.silhouettes.silhouette_offsets`), and whether it ``agrees`` with the keypoints'
    within ``POSITION_AGREEMENT`` frames; where it does, :func:`combined`."""
    timeline, points = triangulated_joints(seen.cameras, seen.frames, seen.people)
    start = [estimates[c.name].get("whole_frames", 0) for c in seen.cameras]
    found = silhouette_offsets(seen.cameras, timeline, folder, points, start, stride)
    out = {}
    for name, entry in estimates.items():
        look = found.get(name) or {}
        if look and "offset_frames" in entry:
            look = dict(look, agrees=bool(abs(look["offset_frames"] - entry["offset_frames"]) <= POSITION_AGREEMENT))
        entry = dict(entry, silhouettes=look) if look else entry
        out[name] = combined(entry) if look.get("agrees") else entry
    return out


def combined(entry: dict) -> dict:
    """A camera's entry with ``offset_frames`` the mean of its keypoints' estimate (kept as ``keypoints``) and its
    silhouettes'. A camera the keypoints left in place whose mean lies within half a frame of step is ``in step``
    (the silhouettes settle what the keypoints' own error called ``uncertain``); a shift of ``CONFIRMED`` frames or
    more that the mean rounds to is of high confidence (one frame is what the keypoints cannot tell from the
    calibration, ``pipelines.prepare.sync.keypoints.MIN_TOTAL_GAIN``, and on the demo both looks then read the cameras
    not cut a frame off as often as the one cut)."""
    keypoints = {"offset_frames": entry["offset_frames"], "method": entry.get("method")}
    mean = round((entry["offset_frames"] + entry["silhouettes"]["offset_frames"]) / 2, 2)
    out = dict(entry, offset_frames=mean, keypoints=keypoints, method=METHOD_COMBINED)
    whole = entry.get("whole_frames", 0)
    if whole == 0 and abs(mean) < 0.5 and entry.get("status") == "uncertain":
        out["status"] = "in step"
    if abs(whole) >= CONFIRMED and int(round(mean)) == whole:
        out["confidence"] = "high"
    return out


def _consistent(estimates: dict[str, dict]) -> bool:
    """Whether the shifts explain every camera: no camera ``uncertain`` (its own error asking for an offset the
    capture's does not confirm) and every shift of high confidence. With another person in some views the
    estimates scatter and fail this."""
    statuses = [(e.get("status"), e.get("confidence")) for e in estimates.values() if "status" in e]
    return all(status != "uncertain" and (status != "out of step" or level == "high") for status, level in statuses)


def crowded_share(people: list[dict]) -> float:
    """The share of the views (camera, frame) with two people or more detected."""
    counts = [len(found) for by_frame in people for found in by_frame.values()]
    return float(np.mean([n >= 2 for n in counts])) if counts else 0.0


def report_followed(seen, found):
    """``seen`` with its ``report``-mode estimates made again on the followed person alone (``found``: the
    ``pipelines.prepare.people.targets.Triangulated`` person, in the views that agreed on them): with other people
    in view, each view's most confident detection, which the first estimate takes, may be somebody else. Other modes
    are returned as they are (their shifts were made before the person was followed)."""
    if seen.sync.get("mode") != "report":
        return seen
    people = [{} for _ in seen.cameras]
    for i, frame in enumerate(found.frames):
        for v in np.flatnonzero(found.used[i]):
            people[v][frame] = [found.distorted[i, v]]
    estimates = find_offsets(seen.cameras, seen.frames, people)
    record = {name: dict(estimates[name], applied_frames=0) for name in estimates}
    note = {"note": seen.sync["note"]} if "note" in seen.sync else {}
    return replace(seen, sync={"mode": "report", "cameras": record, "person": "the person followed", **note})
