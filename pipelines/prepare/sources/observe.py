"""One pass over every camera's recording: frames are resized, written into the capture being built, and their
people (keypoint targets, in the written image's pixels) and person masks are collected.

Keypoints come from BlazePose (``pipelines.prepare.sources.detect``) or from OpenPose JSON files (``--keypoints``);
masks from the segmenter or from mask images (``--masks``), one sub-folder per camera, numbered like the frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from fitting.files import write_image
from pipelines.datasets.camera import Camera, resized_mask
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.keypoints import (
    FILE_LAYOUTS,
    LAYOUT_HINTS,
    LAYOUT_NAMES,
    LAYOUT_SIZES,
    TARGETS,
    frame_number,
    layout_of_25,
    read_openpose,
    to_targets,
)
from pipelines.datasets.rig_files import natural_key
from pipelines.prepare.sources.recordings import (
    IMAGE_SUFFIXES,
    Source,
    frame_count,
    frame_rate,
    read_frames,
    recording_size,
)

#: a video narrower or wider than its calibration window by at most this fraction is taken as the window cropped
#: at its right or bottom edge (the demo's 1080-px videos of a 1088-px window): K is kept
CROP_TOLERANCE = 0.02


@dataclass
class Observations:
    """What the pass found, per camera ``v`` and source frame ``f``.

    Attributes:
        cameras: the output cameras (sizes of the written images, K scaled with them).
        frames: per camera, the source frame indices that were read.
        people: ``people[v][f]`` a list of (T, 3) target arrays (x, y, confidence) in output pixels.
        notes: per camera, lines for the report (size mismatches, resizing).
        corrections: per camera, how far the body fit moved it: (turn in degrees, centre shift in cm).
        depths: per camera, the check of its distance to the person after the body fit
            (``pipelines.prepare.body.camera_depth.DepthCheck.record``); empty when the calibration is kept.
        recordings: per camera, its recording's file or folder name and how the two were matched.
        unused_recordings: recordings that no calibrated camera took (left out of the capture).
        frame_rates: per camera, its video's frame rate as the container states it (None: images, or not stated).
        sync: the cameras' time offsets, estimated and applied (``pipelines.prepare.sync.apply``).
        detections: views detected and reused from the detection cache (``pipelines.prepare.sources.detections``); empty
            when no detector ran.
        person: whom the capture follows and how many people were seen (``pipelines.prepare.run.follow_person``).
        mask_owners: with keypoints from files and masks from the segmenter, per camera and source frame, the
            detector's person (targets) whose mask the view holds, all unseen (confidence 0) where it found nobody
            and gave no mask, no entry where a mask came without a detection; else empty.
    """

    cameras: list[Camera]
    frames: list[list[int]]
    people: list[dict[int, list[np.ndarray]]]
    notes: dict[str, list[str]] = field(default_factory=dict)
    corrections: dict[str, tuple[float, float]] = field(default_factory=dict)
    depths: dict[str, dict] = field(default_factory=dict)
    recordings: dict[str, dict] = field(default_factory=dict)
    unused_recordings: list[str] = field(default_factory=list)
    frame_rates: dict[str, float | None] = field(default_factory=dict)
    sync: dict = field(default_factory=dict)
    detections: dict = field(default_factory=dict)
    person: dict = field(default_factory=dict)
    mask_owners: list[dict[int, np.ndarray]] = field(default_factory=list)


def fit_camera_to_recording(camera: Camera, size: tuple[int, int], source: Source) -> tuple[Camera, str | None]:
    """The camera with the recording's image size: equal sizes, a crop within :data:`CROP_TOLERANCE` (K kept) or
    the same aspect ratio (K scaled); anything else is an error naming the recording."""
    width, height = size
    if camera.width == 0 or (camera.width, camera.height) == size:
        return replace(camera, width=width, height=height), None
    if abs(width - camera.width) <= CROP_TOLERANCE * camera.width and height == camera.height:
        note = f"video is {width}x{height}, the calibration's window {camera.width}x{camera.height}: taken as cropped"
        return replace(camera, width=width, height=height), note
    ratio = width / camera.width
    if abs(height / camera.height - ratio) < 1e-3:
        scaled = camera.scaled(ratio)
        return replace(scaled, width=width, height=height), f"video is {ratio:.3g}x the calibration's size: K scaled"
    raise CaptureError(
        f"{source.path}: frames are {width}x{height} but camera '{camera.name}' of the calibration is "
        f"{camera.width}x{camera.height} (neither a crop nor a scale of it)"
    )


def _numbered_files(folder: Path, suffixes: tuple[str, ...]) -> dict[int, Path]:
    files = sorted((p for p in folder.iterdir() if p.suffix.lower() in suffixes), key=lambda p: natural_key(p.name))
    return {frame_number(p) if suffixes == (".json",) else i: p for i, p in enumerate(files)}


def camera_folder(root: Path, name: str) -> Path:
    """The sub-folder of ``root`` for camera ``name``: ``name``, or one whose name is ``name`` followed by a separator
    and more (``cam01_json``, ``cam01-masks``): ``cam1_json`` is never ``cam10``'s. Several such folders are an
    error naming them."""
    exact = root / name
    if exact.is_dir():
        return exact
    found = sorted(p for p in root.iterdir() if p.is_dir() and _named_after(p.name, name)) if root.is_dir() else []
    if not found:
        raise CaptureError(f"{root}: no sub-folder for camera '{name}'")
    if len(found) > 1:
        raise CaptureError(f"{root}: several sub-folders for camera '{name}' ({', '.join(p.name for p in found)})")
    return found[0]


def _named_after(folder: str, name: str) -> bool:
    """Whether ``folder`` is ``name``, a separator (not a letter or digit) and more."""
    return folder.startswith(name) and len(folder) > len(name) and not folder[len(name)].isalnum()


class _Keypoints:
    """Keypoint targets of one camera, from OpenPose-style files of the recording's ``layout`` (:func:`file_layout`)
    or the detector; with files, the detector's person mask still, when ``need_mask`` (no ``--masks``)."""

    def __init__(self, folder: Path | None, camera: str, detect, layout: str = "blazepose", need_mask=False):
        """``detect(frame, rgb) -> (keypoints or None, mask or None)``: the detector on one view."""
        self.detect, self.files, self.layout, self.need_mask = detect, None, layout, need_mask
        if folder is not None:
            self.files = keypoint_files(folder, camera)

    def __call__(self, frame: int, rgb: np.ndarray, scale: float):
        """(the view's people (targets), its mask or None, the detector's person whose mask it is (targets) when
        the keypoints come from files and the mask from the segmenter, else None)."""
        if self.files is None:
            keypoints, mask = self.detect(frame, rgb)
            return ([] if keypoints is None else [to_targets(keypoints, "blazepose")]), mask, None
        owner, mask = self.detect(frame, rgb) if self.need_mask else (None, None)  # the segmenter's mask, and whose
        if owner is not None:
            owner = to_targets(owner, "blazepose")
        elif mask is None and self.need_mask:  # the detector found nobody: no mask, and nobody's targets
            owner = np.zeros((len(TARGETS), 3))
        path = self.files.get(frame)
        if path is None:
            return [], mask, owner
        people = read_openpose(path)
        if people and len(people[0]) != LAYOUT_SIZES[self.layout]:
            raise CaptureError(
                f"{path}: {len(people[0])} points per person where the recording's files are "
                f"{LAYOUT_NAMES[self.layout]} ({LAYOUT_SIZES[self.layout]} points)"
            )
        targets = [to_targets(p, self.layout) for p in people]
        for t in targets:
            t[:, :2] *= scale
        return targets, mask, owner


def keypoint_files(folder: Path, camera: str) -> dict[int, Path]:
    """Camera ``camera``'s keypoint files under ``folder``, by frame number."""
    where = camera_folder(folder, camera)
    files = _numbered_files(where, (".json",))
    if not files:
        raise CaptureError(f"{where}: no OpenPose *_keypoints.json files")
    return files


def file_layout(folder: Path, cameras: list[str], given: str | None, sample: int = 30) -> str:
    """The keypoint layout of the recording's files under ``folder`` (one detector made them all): ``given``
    (``--keypoint-layout``) when their size agrees, else the only layout of their size; 25 points are checked
    (``layout_of_25``) over every camera together, and refused when the check cannot tell, or when it contradicts
    ``given``. Reads up to ``sample`` files per camera, spread over the recording."""
    people, first = [], None
    for camera in cameras:
        files = list(keypoint_files(folder, camera).values())
        for path in files[:: max(1, len(files) // sample)]:
            found = read_openpose(path)
            if found and not people:
                first = path
            if found and people and len(found[0]) != len(people[0]):
                raise CaptureError(
                    f"{folder}: files of different layouts: {len(people[0])} points per person in {first}, "
                    f"{len(found[0])} in {path}"
                )
            people += found
    if not people:
        return given or "body25"
    size = len(people[0])
    if given is not None and LAYOUT_SIZES[given] != size:
        raise CaptureError(
            f"{folder}: {size} points per person, but --keypoint-layout {given} has {LAYOUT_SIZES[given]}"
        )
    candidates = FILE_LAYOUTS[size]
    if len(candidates) == 1:
        return candidates[0]
    told = layout_of_25(people)
    if given is not None and told is not None and told != given:
        raise CaptureError(
            f"{folder}: these 25-point keypoints are {LAYOUT_NAMES[told]} ({LAYOUT_HINTS[told]}), not "
            f"{LAYOUT_NAMES[given]}; give --keypoint-layout {told}"
        )
    if given is None and told is None:
        raise CaptureError(
            f"{folder}: 25-point keypoints, and their points cannot tell BODY_25 from BODY_25B; give "
            "--keypoint-layout body25 or body25b"
        )
    return given or told


def observe(
    pairs: list[tuple[Camera, Source]],
    wanted: range,
    out: Path,
    longest_side: int | None,
    keypoints: Path | None,
    masks: Path | None,
    detector,
    progress,
    keypoint_layout: str | None = None,
) -> Observations:
    """Read every camera, write ``<camera>/<frame:06d>.jpg`` and ``mask_raw/<camera>/<frame:06d>.png`` under
    ``out`` (named by source frame index; renumbered later), and collect people (module docstring)."""
    cameras, frames, people, owners, notes = [], [], [], [], {}
    layout = "blazepose" if keypoints is None else file_layout(keypoints, [s.name for _, s in pairs], keypoint_layout)
    for camera, source in pairs:
        size = recording_size(source)
        camera, note = fit_camera_to_recording(camera, size, source)
        notes[camera.name] = [note] if note else []
        scale = min(1.0, longest_side / max(size)) if longest_side else 1.0
        if scale < 1:
            camera = camera.scaled(scale)
            notes[camera.name].append(f"frames resized by {scale:.4g} to {camera.width}x{camera.height}")
        found = _Keypoints(keypoints, source.name, _view_detector(detector, source), layout, need_mask=masks is None)
        if found.files is not None:
            notes[camera.name].append(f"keypoints read as {LAYOUT_NAMES[found.layout]}")
        mask_files = _numbered_files(camera_folder(masks, source.name), IMAGE_SUFFIXES) if masks else None
        (out / camera.name).mkdir(parents=True, exist_ok=True)
        (out / "mask_raw" / camera.name).mkdir(parents=True, exist_ok=True)
        seen, by_frame, owned = [], {}, {}
        for index, bgr in read_frames(source, wanted):
            if scale < 1:
                bgr = cv2.resize(bgr, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            by_frame[index], mask, owner = found(index, rgb, scale)
            if owner is not None:
                owned[index] = owner
            if mask_files is not None:
                mask = _given_mask(mask_files, index, camera, size)
            if mask is None:
                mask = np.zeros(bgr.shape[:2], bool)
            write_image(out / camera.name / f"{index:06d}.jpg", bgr, (cv2.IMWRITE_JPEG_QUALITY, 95))
            write_image(out / "mask_raw" / camera.name / f"{index:06d}.png", mask.astype(np.uint8))
            seen.append(index)
            progress()
        cameras.append(camera)
        frames.append(seen)
        people.append(by_frame)
        owners.append(owned)
    from_segmenter = keypoints is not None and masks is None
    return Observations(cameras, frames, people, notes, mask_owners=owners if from_segmenter else [])


def read_recordings(folder: Path, sources, detector, request) -> Observations:
    """The sources stage of a prepare: every camera's frames ``request.start:stop:stride`` read once into ``folder``
    with their people and masks (:func:`observe`), and where each recording came from. ``sources``: the matched
    (camera, source, how) triples and the names of the recordings no camera took."""
    from tqdm import tqdm

    matched, unused = sources
    pairs = [(camera, source) for camera, source, _ in matched]
    wanted = range(request.start, request.stop if request.stop is not None else 10**9, request.stride)
    counts = [frame_count(source) for _, source in pairs]  # for the bar's ETA only
    total = None if None in counts else sum(len(range(wanted.start, min(wanted.stop, n), wanted.step)) for n in counts)
    with tqdm(total=total, desc="reading frames", unit="view", disable=not request.progress) as bar:
        seen = observe(
            pairs,
            wanted,
            folder,
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
    return seen


def _view_detector(detector, source: Source):
    """``detect(frame, rgb)`` for one recording: through the detection cache when ``detector`` is one
    (``pipelines.prepare.sources.detections.CachedDetector``), else the plain detector."""
    if hasattr(detector, "for_source"):
        return detector.for_source(source)
    return lambda frame, rgb: detector(rgb)


def _given_mask(files: dict[int, Path], index: int, camera: Camera, recorded: tuple[int, int]) -> np.ndarray:
    """Frame ``index``'s mask from ``files``: the recording's size (``recorded``, width x height), resized with
    its frames; another size is refused."""
    path = files.get(index)
    if path is None:
        raise CaptureError(f"no mask for frame {index} of camera '{camera.name}' (--masks lists {len(files)} files)")
    raw = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if raw is None:
        raise CaptureError(f"{path}: unreadable mask image")
    if raw.shape != (camera.height, camera.width):
        if raw.shape != (recorded[1], recorded[0]):
            raise CaptureError(
                f"{path}: mask is {raw.shape[1]}x{raw.shape[0]}, camera '{camera.name}' records "
                f"{recorded[0]}x{recorded[1]}"
            )
        # as --resolution resizes the frames, by area, so that each pixel is centred where the camera's rays go
        # (docs/formats.md §0): the person's where they cover most of it
        return resized_mask(raw > 0, (camera.width, camera.height))
    return raw > 0
