"""``prepare_capture``: a multi-camera recording and its calibration in, a ZJU-MoCap-layout capture out
(docs/guides/real-captures.md). The stages, each a sub-package, in the order :func:`_build` runs them:

1. ``sources/``: the recordings matched to the calibration's cameras, every frame read once, with its people (keypoint
   files or the detector, whose results are cached beside the capture) and masks;
2. ``sync/``: the cameras put in step (their time offsets from the keypoints and from the silhouettes);
3. ``people/``: whom the capture follows, tracked and triangulated in every frame, the views of other people left out;
4. ``body/``: the body fitted to that person's targets and masks, the cameras corrected and their distances checked;
5. ``layout/``: the capture written in the ZJU-MoCap layout with its masks, overlays, checks, colour and report.

Everything is written into a hidden ``.<out>.partial`` folder beside ``out`` and renamed at the end, so an
interrupted run leaves nothing that looks finished.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from fitting.files import folder_lock, fresh_partial, publish_folder, restore_replaced
from pipelines.body.locate import BODY_MODEL_RECORD, body_model_record
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.rig_files import read_rig
from pipelines.prepare.body.bodies import fit_bodies
from pipelines.prepare.layout.write import write_capture
from pipelines.prepare.people.follow import follow_person
from pipelines.prepare.request import PrepareRequest
from pipelines.prepare.sources.detections import report_detections
from pipelines.prepare.sources.observe import read_recordings
from pipelines.prepare.sources.recordings import find_sources, match_cameras
from pipelines.prepare.sync.apply import report_followed, synchronise

CALIBRATION_PATTERNS = ("*.qca.txt", "*.toml", "intri.yml", "annots.npy")
MARKER = "prepared.json"


def _build(staging: Path, sources, detector, body, holdout, calibration, request: PrepareRequest) -> dict:
    """The stages in order (module docstring), from the matched recordings (``sources``: the (camera, source, how)
    triples and the names of the recordings no camera took) to the finished capture in ``staging``; returns the
    report."""
    frames = staging / ".frames"
    seen = read_recordings(frames, sources, detector, request)
    seen = synchronise(seen, frames, request.sync, request.stride)
    found = follow_person(frames, seen, detector, request)
    seen = report_followed(seen, found)
    seen = report_detections(seen, detector)
    seen, fitted, vertices = fit_bodies(staging, seen, found, body, request)
    return write_capture(staging, seen, found, fitted, vertices, body.faces, holdout, request, calibration)


def prepare_capture(request: PrepareRequest) -> dict:
    """Run every stage (module docstring); returns the report. On any error or Ctrl-C the partial folder is removed.
    One writer per ``out`` (``fitting.files.folder_lock``)."""
    with folder_lock(Path(request.out)):
        return _prepare_locked(request)


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
        from pipelines.prepare.sources.detect import BlazePose, detector_id
        from pipelines.prepare.sources.detections import CachedDetector, detections_folder

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
    if detector is not None:  # the finished prepare keeps what it used (pipelines.prepare.sources.detections)
        detector.prune()
    return report


def _holdout(name: str | None, names: list[str]) -> str | None:
    """The novel-view camera: ``name``, ``none``, or by default the last camera when there are at least three."""
    if name is None:
        return names[-1] if len(names) >= 3 else None
    if name.lower() == "none":
        return None
    if name not in names:
        raise CaptureError(f"--holdout-camera {name}: not one of the cameras {names}")
    return name
