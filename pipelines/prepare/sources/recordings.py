"""The recording's cameras: one video file or one image folder per camera, matched to the calibration's cameras.

Frames are synchronised by index: frame ``i`` of every camera shows the same instant. Videos are decoded frame by
frame (their container's frame count and duration are not trusted: one demo video reports a longer duration than
its 100 frames), image folders are read in natural order of their file names.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipelines.datasets.camera import Camera
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.images import read_image
from pipelines.datasets.rig_files import natural_key

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class Source:
    """One camera's recording: a video file or a folder of images (``is_video``)."""

    name: str
    path: Path
    is_video: bool


def find_sources(folder: Path) -> list[Source]:
    """Videos in ``folder`` (or ``folder/videos``), else its sub-folders holding images, in natural order."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CaptureError(f"{folder}: no such folder of videos or per-camera image folders")
    for place in (folder, folder / "videos"):
        videos = (
            [p for p in place.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES] if place.is_dir() else []
        )
        if videos:
            stems = [p.stem for p in videos]
            twice = sorted({stem for stem in stems if stems.count(stem) > 1})
            if twice:
                names = sorted(p.name for p in videos if p.stem == twice[0])
                raise CaptureError(f"{place}: camera '{twice[0]}' has several videos ({', '.join(names)}); keep one")
            return [Source(p.stem, p, True) for p in sorted(videos, key=lambda p: natural_key(p.name))]
        folders = [p for p in place.iterdir() if p.is_dir() and _images(p)] if place.is_dir() else []
        if folders:
            return [Source(p.name, p, False) for p in sorted(folders, key=lambda p: natural_key(p.name))]
    raise CaptureError(
        f"{folder}: no videos ({', '.join(VIDEO_SUFFIXES)}) and no per-camera image folders in it or in its videos/"
    )


def _images(folder: Path) -> list[Path]:
    return sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=lambda p: natural_key(p.name)
    )


def name_key(name: str) -> str:
    """A camera name without case, separators or zero padding: ``cam_01``, ``Cam1`` and ``CAM-001`` -> ``cam1``."""
    text = re.sub(r"[\s_\-.]+", "", name.lower())
    return re.sub(r"\d+", lambda m: str(int(m.group())), text)


def match_cameras(
    cameras: list[Camera], sources: list[Source], mapping: dict[str, str] | None = None
) -> list[tuple[Camera, Source, str]]:
    """Pair calibration cameras with recordings, and say how each pair was made: an explicit ``{camera: source}``
    mapping; else equal names, then names equal but for case, separators and zero padding (:func:`name_key`, each
    key unique on both sides); else natural order when the counts agree (Pose2Sim's rule). Cameras without a
    recording are left out."""
    by_name = {s.name: s for s in sources}
    if mapping:
        return _mapped(cameras, by_name, mapping)
    pairs = [(c, by_name[c.name], "name") for c in cameras if c.name in by_name]
    taken = {c.name for c, _, _ in pairs} | {s.name for _, s, _ in pairs}
    keys = {}
    for item in [*(c for c in cameras if c.name not in taken), *(s for s in sources if s.name not in taken)]:
        keys.setdefault((isinstance(item, Source), name_key(item.name)), []).append(item)
    for (is_source, key), items in keys.items():
        partners = keys.get((True, key), [])
        if not is_source and len(items) == 1 and len(partners) == 1:
            pairs.append((items[0], partners[0], "name, up to case, separators and zero padding"))
    if len(pairs) >= 2:
        order = {c.name: i for i, c in enumerate(cameras)}
        return sorted(pairs, key=lambda pair: order[pair[0].name])
    if len(cameras) == len(sources):
        return [(c, s, "order (natural sort of both)") for c, s in zip(cameras, sources)]
    if len(pairs) == 1:
        camera, source, _ = pairs[0]
        raise CaptureError(
            f"only camera '{camera.name}' of the calibration's {[c.name for c in cameras]} has a recording "
            f"({source.path.name}) among {[s.name for s in sources]}; a capture needs two cameras, or give "
            "--camera-map CAM=RECORDING,..."
        )
    raise CaptureError(
        f"the calibration's cameras {[c.name for c in cameras]} match none of the recordings "
        f"{[s.name for s in sources]} by name, and their counts differ ({len(cameras)} vs {len(sources)}); "
        "give --camera-map CAM=RECORDING,..."
    )


def _mapped(cameras: list[Camera], by_name: dict[str, Source], mapping: dict[str, str]):
    """The pairs ``--camera-map`` gives; a name it does not know, or a recording behind two cameras, is refused."""
    cams = {c.name: c for c in cameras}
    unknown = [k for k in mapping if k not in cams] + [v for v in mapping.values() if v not in by_name]
    if unknown:
        raise CaptureError(
            f"--camera-map names {unknown} that are not calibration cameras ({sorted(cams)}) or recordings "
            f"({sorted(by_name)})"
        )
    twice = sorted({v for v in mapping.values() if list(mapping.values()).count(v) > 1})
    if twice:
        both = [k for k, v in mapping.items() if v == twice[0]]
        raise CaptureError(f"--camera-map puts recording {twice[0]} behind several cameras ({', '.join(both)})")
    return [(cams[k], by_name[v], "--camera-map") for k, v in mapping.items()]


def read_frames(source: Source, wanted: range) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (frame index, BGR uint8 image) for the frames of ``wanted`` that the recording has, in order.

    An undecodable video or image is an error naming the file; a recording shorter than ``wanted`` just ends.
    """
    if not source.is_video:
        files = _images(source.path)
        for index in wanted:
            if index >= len(files):
                return
            image = read_image(files[index])
            yield index, image
        return
    with native_stderr_to_null():  # ffmpeg's own complaint ("moov atom not found"): our line names the file
        video = cv2.VideoCapture(str(source.path))
    try:
        if not video.isOpened():
            raise CaptureError(f"{source.path}: cannot be decoded as a video")
        index = -1
        while index + 1 < wanted.stop:
            ok, image = video.read()
            if not ok:
                if index < 0:
                    raise CaptureError(f"{source.path}: cannot be decoded as a video (no frame could be read)")
                return
            index += 1
            if index in wanted:
                yield index, image
    finally:
        video.release()


def frame_rate(source: Source) -> float | None:
    """A video's frame rate as its container states it (None for image folders or when it states none)."""
    if not source.is_video:
        return None
    rate = _stated(source, cv2.CAP_PROP_FPS)
    return float(rate) if rate and np.isfinite(rate) else None


def frame_count(source: Source) -> int | None:
    """The frames a recording holds: its images, or the count its video container states (None when it states
    none; the stated count can be off by a frame or two, so it sizes progress bars, never the frames read)."""
    if not source.is_video:
        return len(_images(source.path))
    count = _stated(source, cv2.CAP_PROP_FRAME_COUNT)
    return int(count) if count and np.isfinite(count) and count > 0 else None


def _stated(source: Source, prop: int) -> float:
    """A property of a video as OpenCV reads it from the container (0 when the video cannot be opened)."""
    with native_stderr_to_null():
        video = cv2.VideoCapture(str(source.path))
    try:
        return video.get(prop) if video.isOpened() else 0.0
    finally:
        video.release()


@contextlib.contextmanager
def native_stderr_to_null():
    """What native code (ffmpeg through OpenCV) writes to file descriptor 2 during the block goes to the null
    device; Python's own stderr is flushed first."""
    sys.stderr.flush()
    saved, null = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 2)
        yield
    finally:
        _flush_c_streams()  # what C's stdio still buffers goes to the null device too
        os.dup2(saved, 2)
        os.close(saved)
        os.close(null)


def _flush_c_streams() -> None:
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):  # no C library to ask: nothing buffered there either
        pass


def recording_size(source: Source) -> tuple[int, int]:
    """(width, height) of a recording's first frame."""
    for _, image in read_frames(source, range(1)):
        return image.shape[1], image.shape[0]
    raise CaptureError(f"{source.path}: no frames")
