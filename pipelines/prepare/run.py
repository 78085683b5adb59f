"""``prepare_capture``: a multi-camera recording and its calibration in, a ZJU-MoCap-layout capture out
(docs/guides/real-captures.md).

Everything is written into a hidden ``.<out>.partial`` folder beside ``out`` and renamed at the end, so an
interrupted run leaves nothing that looks finished.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from fitting.files import folder_lock, fresh_partial, publish_folder, restore_replaced
from pipelines.body.locate import BODY_MODEL_RECORD, body_model_record
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.floor import Floor, camera_up, floor_from_feet, write_floor
from pipelines.datasets.rig_files import read_rig
from pipelines.prepare.body_fit import FitSettings, fit_body, fit_steps, fitted_vertices
from pipelines.prepare.camera_depth import check_camera_depths
from pipelines.prepare.layout import finish_capture, write_sequence
from pipelines.prepare.observe import observe
from pipelines.prepare.people import choose_track, guide
from pipelines.prepare.person_targets import find_tracks, triangulate_people
from pipelines.prepare.silhouettes import silhouette_stage
from pipelines.prepare.sources import find_sources, frame_count, frame_rate, match_cameras
from pipelines.prepare.sync_apply import report_followed, synchronise

CALIBRATION_PATTERNS = ("*.qca.txt", "*.toml", "intri.yml", "annots.npy")
MARKER = "prepared.json"


@dataclass(frozen=True)
class PrepareRequest:
    """What ``narf-prepare-capture`` was asked (its ``--help`` says each)."""

    recording: Path
    out: Path
    calibration: Path | None = None
    start: int = 0
    stop: int | None = None
    stride: int = 1
    longest_side: int | None = None
    keypoints: Path | None = None
    keypoint_layout: str | None = None  # None: from the files' size (25 points checked)
    masks: Path | None = None
    camera_map: dict[str, str] | None = None
    holdout_camera: str | None = None
    novel_fraction: float = 0.3
    threshold: float = 0.03
    smpl_dir: Path | None = None
    fit: FitSettings = field(default_factory=FitSettings)
    floor: Floor | None = None  # None: found from the fitted feet
    overwrite: bool = False
    keep_flagged: bool = False  # write the capture even when every camera is flagged (for inspection)
    smpl_params: Path | None = None  # bodies the user brings (EasyMocap smpl/*.json or ZJU params/), not fitted
    person: int | None = None  # the person's id in smpl_params (None: the only one)
    follow: str | tuple = "best-seen"  # whom to follow among several people (prepare.people.parse_person)
    sync: str | dict[str, int] = "auto"  # auto, report, off, or whole-frame offsets by camera (prepare.sync_apply)
    progress: bool = True


def find_calibration(recording: Path) -> Path:
    """The one calibration file in ``recording/calibration/`` or ``recording/`` (error if none or several)."""
    for place in (recording / "calibration", recording):
        found = sorted({p for pattern in CALIBRATION_PATTERNS for p in place.glob(pattern)}) if place.is_dir() else []
        if len(found) == 1:
            return found[0].parent if found[0].name == "intri.yml" else found[0]
        if len(found) > 1:
            raise CaptureError(
                f"{place}: several calibrations ({', '.join(p.name for p in found)}); pick one with --calibration"
            )
    raise CaptureError(f"{recording}: no calibration found in calibration/ or beside the videos; give --calibration")


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not (out / MARKER).is_file():
        raise CaptureError(f"{out}: exists and is not a capture prepared by this tool; choose a new --out")
    if out.exists() and not overwrite:
        raise CaptureError(f"{out}: already prepared; pass --overwrite to replace it")


def _refuse_all_flagged(report: dict, request: PrepareRequest) -> None:
    """A capture whose every camera is flagged is not a capture: refused, unless ``keep_flagged`` asks for it."""
    flagged = report["flagged_cameras"]
    if request.keep_flagged or len(flagged) < len(report["cameras"]):
        return
    name, reason = next(iter(flagged.items()))
    raise CaptureError(
        f"{request.recording}: every camera is flagged ({name}: {reason}); nothing was written "
        "(--keep-flagged writes it for inspection)"
    )


def prepare_capture(request: PrepareRequest) -> dict:
    """Run every step (module docstring); returns the report. On any error or Ctrl-C the partial folder is removed.
    One writer per ``out`` (``fitting.files.folder_lock``)."""
    with folder_lock(Path(request.out)):
        return _prepare_locked(request)


def _prepare_locked(request: PrepareRequest) -> dict:
    from pipelines.body.model import BodyModel

    out = Path(request.out)
    restore_replaced(out)  # a replacement killed halfway: the old capture first
    _check_out(out, request.overwrite)
    sources = find_sources(request.recording)  # a missing recording is named before its calibration is looked for
    calibration = request.calibration or find_calibration(Path(request.recording))
    matched = match_cameras(read_rig(calibration), sources, request.camera_map)
    pairs = [(camera, source) for camera, source, _ in matched]
    names = [c.name for c, _ in pairs]
    if len(set(names)) != len(names) or any("/" in n or n.startswith(".") for n in names):
        raise CaptureError(f"{calibration}: camera names must be distinct folder names, got {names}")
    holdout = _holdout(request.holdout_camera, names)
    if isinstance(request.follow, tuple) and request.follow[0] == "pixel" and request.follow[1] not in names:
        raise CaptureError(
            f"--person pixel:{request.follow[1]}:...: {request.follow[1]} is not one of the cameras {names}"
        )
    if isinstance(request.sync, dict) and set(request.sync) - set(names):  # before any frame is read
        raise CaptureError(f"--sync: {', '.join(sorted(set(request.sync) - set(names)))} not among the cameras {names}")
    detector = None
    if request.keypoints is None or request.masks is None:
        from pipelines.prepare.detect import BlazePose, detector_id
        from pipelines.prepare.detections import CachedDetector, detections_folder

        detector = CachedDetector(BlazePose(), detections_folder(out), detector_id())
    body = BodyModel(request.smpl_dir)  # a bad --smpl-dir fails before any frame is read
    staging = fresh_partial(out)
    try:
        unused = [s.name for s in sources if s.name not in {source.name for _, source, _ in matched}]
        report = _build(staging, (matched, unused), detector, body, holdout, calibration, request)
        _refuse_all_flagged(report, request)
        (staging / BODY_MODEL_RECORD).write_text(json.dumps(body_model_record(body.path), indent=1))
        (staging / MARKER).write_text(
            json.dumps({"recording": str(request.recording), "calibration": str(calibration)})
        )
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    publish_folder(staging, out)
    if detector is not None:  # the finished prepare keeps what it used (pipelines.prepare.detections)
        detector.prune()
    return report


def _build(staging: Path, sources, detector, body, holdout, calibration, request: PrepareRequest) -> dict:
    """Everything between the matched recordings (``sources``: the (camera, source, how) pairs and the names of the
    recordings no camera took) and the finished capture in ``staging``; returns the report."""
    matched, unused = sources
    pairs = [(camera, source) for camera, source, _ in matched]
    wanted = range(request.start, request.stop if request.stop is not None else 10**9, request.stride)
    counts = [frame_count(source) for _, source in pairs]  # for the bar's ETA only
    total = None if None in counts else sum(len(range(wanted.start, min(wanted.stop, n), wanted.step)) for n in counts)
    with tqdm(total=total, desc="reading frames", unit="view", disable=not request.progress) as bar:
        seen = observe(
            pairs,
            wanted,
            staging / ".frames",
            request.longest_side,
            request.keypoints,
            request.masks,
            detector,
            bar.update,
            request.keypoint_layout,
        )
    seen.recordings = {c.name: {"recording": s.path.name, "matched_by": how} for c, s, how in matched}
    seen.unused_recordings = unused
    seen.frame_rates = {c.name: frame_rate(s) for c, s, _ in matched}
    seen = synchronise(seen, staging / ".frames", request.sync, request.stride)
    common = sorted(set.intersection(*(set(f) for f in seen.frames)))
    if not common:
        raise CaptureError(f"{request.recording}: the cameras share no frame in {wanted.start}:{request.stop or ''}")
    found = follow_person(staging / ".frames", seen, common, detector, request)
    seen = report_followed(seen, found)
    if detector is not None:  # the cache stays for the next run with this --out (docs/guides/real-captures.md)
        files, size = detector.used_size()
        seen.detections = {
            "reused": detector.reused,
            "detected": detector.detected,
            "cache": str(detector.folder),
            "cache_files": files,
            "cache_mb": round(size / 1e6, 1),
        }
    settings, start = request.fit, None
    if request.smpl_params is not None:  # the user's bodies, polished by the silhouette stage only
        start = brought_bodies(request.smpl_params, found.frames, request.person)
        settings = replace(settings, global_iterations=0, iterations=0)
    inputs = _fit_inputs(seen.cameras, found)
    steps = fit_steps(settings, len(found.frames), bool(settings.silhouette_iterations))
    masks = None
    if request.fit.silhouette_iterations:
        masks = silhouette_stage(staging, seen.cameras, found, body.faces, inputs[0])
    rig = (np.stack([c.K for c in seen.cameras]), np.stack([c.cam_from_world for c in seen.cameras]))
    with tqdm(total=steps, desc="fitting the body", disable=not request.progress) as bar:
        fitted = fit_body(body, *inputs, settings, lambda done, total: bar.update(1), masks, rig, start)
    vertices = fitted_vertices(body, fitted)
    if fitted.cam_from_world is not None:  # the capture's cameras are the corrected ones (docs/guides/real-captures.md)
        seen = corrected_cameras(seen, fitted.cam_from_world)
        seen = check_camera_depths(staging, seen, found, vertices, body.faces)
    write_sequence(staging, seen.cameras, found, fitted, vertices)
    floor = request.floor or floor_from_feet(vertices, camera_up(seen.cameras))
    write_floor(staging, floor)
    return finish_capture(staging, seen, found, fitted, vertices, body.faces, holdout, request, calibration, floor)


#: with several people and ``--person best-seen``, each is looked for in every view of one frame in this many
#: before the choice (docs/guides/real-captures.md, *Other people in view*)
CHOICE_STRIDE = 10


def follow_person(folder: Path, seen, frames: list[int], detector, request: PrepareRequest):
    """The person ``request.follow`` picks, triangulated in ``frames`` (``pipelines.prepare.people``). With a
    ``detector`` and keypoints from it, views that missed a person are detected again around them
    (:func:`_look_again`); with keypoints from files and masks from the detector's segmenter, views whose mask came
    with somebody else's detection are (``redetect_masks``). Views where other people overlap the person are left
    out (``pipelines.prepare.occlusion``). Every used view's mask is the person's (their crop's, or
    the whole image's when its detection is theirs; a view with only somebody else's is no longer used), cut to them.
    ``seen.people`` gains the crops' detections (keypoints from the detector) and ``seen.person`` says whom."""
    from pipelines.prepare.crops import crop_masks, cut_masks, redetect_masks
    from pipelines.prepare.occlusion import leave_out_overlapped

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
    """The tracks of keypoint files that the views' masks show (``pipelines.prepare.people.mask_support`` at least
    ``MASK_SUPPORT``, on one frame of ``CHOICE_STRIDE``), and how many were dropped; all of them when none is
    shown (the masks then say nothing of whom to follow)."""
    import cv2

    from pipelines.prepare.people import MASK_SUPPORT, mask_support

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
    (``pipelines.prepare.crops.redetect``): for ``best-seen`` with several people, each of them in one frame of
    ``CHOICE_STRIDE`` before the choice; then the chosen one in every frame. Returns the tracks found again, the
    chosen one's index, the line saying whom, the crops and the number of views detected again."""
    from pipelines.prepare.crops import redetect
    from pipelines.prepare.people import nearest_track

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


def brought_bodies(folder: Path, frames: list[int], person: int | None):
    """``fit_body``'s ``start`` from the bodies of ``folder`` (``pipelines.datasets.smpl_params``) for source
    ``frames``: poses with their first three values folded into Rh (R(Rh) R(poses[:3]) is the body's turn), Th, and
    the frames' median shape (the capture keeps one shape)."""
    from pipelines.datasets.smpl_params import bodies_for_frames

    bodies = bodies_for_frames(folder, frames, person)
    poses = np.stack([b.poses for b in bodies]).astype(np.float64)
    turn = Rotation.from_rotvec(np.stack([b.rh for b in bodies])) * Rotation.from_rotvec(poses[:, :3])
    poses[:, :3] = 0
    shapes = np.median(np.stack([b.shapes for b in bodies]), axis=0)
    return poses, turn.as_rotvec(), np.stack([b.th for b in bodies]).astype(np.float64), shapes


def corrected_cameras(seen, cam_from_world: np.ndarray):
    """``seen`` with each camera's extrinsics replaced by the body fit's corrected (V, 3, 4) ones, and how far each
    moved (degrees, centimetres) in ``seen.corrections``."""
    cameras, corrections = [], {}
    for camera, corrected in zip(seen.cameras, cam_from_world):
        pose = np.eye(4)
        pose[:3] = corrected
        moved = replace(camera, cam_from_world=pose)
        turn = Rotation.from_matrix(pose[:3, :3] @ camera.cam_from_world[:3, :3].T).magnitude()
        corrections[camera.name] = (float(np.degrees(turn)), float(100 * np.linalg.norm(moved.centre - camera.centre)))
        cameras.append(moved)
    return replace(seen, cameras=cameras, corrections=corrections)


def _fit_inputs(cameras, found):
    from pipelines.prepare.multiview import projection_matrix

    P = np.stack([projection_matrix(c) for c in cameras])
    heights = np.array([c.height for c in cameras], np.float64)
    return P, heights, found.keypoints, found.points


def _holdout(name: str | None, names: list[str]) -> str | None:
    """The novel-view camera: ``name``, ``none``, or by default the last camera when there are at least three."""
    if name is None:
        return names[-1] if len(names) >= 3 else None
    if name.lower() == "none":
        return None
    if name not in names:
        raise CaptureError(f"--holdout-camera {name}: not one of the cameras {names}")
    return name
