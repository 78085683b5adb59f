"""The detector's results kept on disk, so that a rerun of ``narf-prepare-capture`` (after a kill, or with
``--overwrite`` and other fitting settings) detects each view once (docs/guides/real-captures.md, *Long takes*).

Each view's keypoints and person mask go in one small file under ``.<capture>.detections/`` beside the capture,
named by a hash of what decides them: the recording (its path, size and modification time), the frame, the size of
the image given to the detector and the detector (its name and settings). A changed video, another ``--resolution``
or another detector finds no file and detects again. Files are written atomically; one that cannot be read is
detected again and replaced."""

from __future__ import annotations

import hashlib
import io
import shutil
from pathlib import Path

import numpy as np

from fitting.files import atomic_write_bytes
from pipelines.prepare.sources.recordings import Source


def detections_folder(out: Path) -> Path:
    """The cache of the capture ``out``: ``.<name>.detections`` beside it."""
    out = Path(out)
    return out.parent / f".{out.name}.detections"


class CachedDetector:
    """``detector`` (``rgb -> (keypoints or None, mask or None)``) with its results kept in ``folder``.

    ``cache(source, frame, rgb)``, or ``cache.for_source(source)(frame, rgb)``; ``reused`` and ``detected`` count
    the views of this run, ``used`` holds the files it read or wrote, and :meth:`prune` removes every other file
    (a finished prepare keeps what it used: reruns at another resolution, on a re-encoded video or with other
    people painted out would otherwise add a full set each)."""

    def __init__(self, detector, folder: Path, detector_id: str):
        self.detector, self.folder, self.detector_id = detector, Path(folder), detector_id
        self.reused = self.detected = 0
        self.used: set[Path] = set()
        self._recordings: dict[Path, str] = {}

    def _recording_id(self, source: Source) -> str:
        path = Path(source.path).resolve()
        if path not in self._recordings:
            stat = path.stat()
            if path.is_dir():  # a folder of images: its files' names, sizes and times
                stats = [(p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(path.iterdir())]
                self._recordings[path] = f"{path}|{stats}"
            else:
                self._recordings[path] = f"{path}|{stat.st_size}|{stat.st_mtime_ns}"
        return self._recordings[path]

    def path(self, source: Source, frame: int, shape: tuple[int, ...]) -> Path:
        """The file of one view's detection."""
        key = f"{self._recording_id(source)}|{frame}|{tuple(shape)}|{self.detector_id}"
        digest = hashlib.sha256(key.encode()).hexdigest()[:32]
        return self.folder / digest[:2] / f"{digest}.npz"

    def __call__(self, source: Source, frame: int, rgb: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The detection of ``source``'s ``frame`` (``rgb`` (H, W, 3)): read back when kept, else detected and
        kept."""
        path = self.path(source, frame, rgb.shape)
        self.used.add(path)
        kept = _read(path, rgb.shape[:2])
        if kept is not None:
            self.reused += 1
            return kept
        keypoints, mask = self.detector(rgb)
        atomic_write_bytes(path, _encode(keypoints, mask))
        self.detected += 1
        return keypoints, mask

    def crop(self, rgb: np.ndarray, box: tuple[int, int, int, int]):
        """The detection of ``rgb`` (H, W, 3: a crop of a view) whose top-left corner is ``box[:2]`` of the whole
        image: keypoints in the whole image's pixels, the mask (of the crop's size) and the cache key of the
        detection (:meth:`kept_crop`). Kept under the hash of the crop's pixels and the detector (a crop is asked for
        after the frames are written and shifted into step, and with other people painted out, so its pixels, not
        the recording, name it)."""
        key = hashlib.sha256(np.ascontiguousarray(rgb).tobytes() + str(rgb.shape).encode()).hexdigest()
        kept = self.kept_crop(key, rgb.shape[:2])
        if kept is not None:
            self.reused += 1
            keypoints, mask = kept
        else:
            keypoints, mask = self.detector(np.ascontiguousarray(rgb))
            atomic_write_bytes(self._crop_path(key), _encode(keypoints, mask))
            self.detected += 1
        if keypoints is not None:
            keypoints = keypoints + np.array([box[0], box[1], 0.0])
        return keypoints, mask, key

    def kept_crop(self, key: str, shape: tuple[int, int]):
        """The kept (keypoints in the crop's pixels, mask) of the crop ``key`` (:meth:`crop`), or None."""
        return _read(self._crop_path(key), shape)

    def _crop_path(self, key: str) -> Path:
        digest = hashlib.sha256(f"{key}|{self.detector_id}".encode()).hexdigest()[:32]
        path = self.folder / "crops" / digest[:2] / f"{digest}.npz"
        self.used.add(path)
        return path

    def used_size(self) -> tuple[int, int]:
        """(files, bytes) of the detections this run read or wrote."""
        sizes = [p.stat().st_size for p in self.used if p.is_file()]
        return len(sizes), sum(sizes)

    def prune(self) -> int:
        """Remove every kept detection this run did not use (and the folders left empty); returns how many."""
        removed = 0
        for path in self.folder.rglob("*.npz"):
            if path not in self.used:
                path.unlink(missing_ok=True)
                removed += 1
        for folder in sorted((p for p in self.folder.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts)):
            if not any(folder.iterdir()):
                folder.rmdir()
        return removed

    def for_source(self, source: Source):
        """``detect(frame, rgb)`` of one recording."""
        return lambda frame, rgb: self(source, frame, rgb)

    def clear(self) -> None:
        """Remove the cache (all of it)."""
        shutil.rmtree(self.folder, ignore_errors=True)


def report_detections(seen, detector: CachedDetector | None):
    """``seen`` with how many views the cache gave back and how many were detected, and the cache's size
    (``seen.detections``; nothing without a detector). The cache stays for the next run with the same ``--out``
    (docs/guides/real-captures.md)."""
    if detector is not None:
        files, size = detector.used_size()
        seen.detections = {
            "reused": detector.reused,
            "detected": detector.detected,
            "cache": str(detector.folder),
            "cache_files": files,
            "cache_mb": round(size / 1e6, 1),
        }
    return seen


def _encode(keypoints: np.ndarray | None, mask: np.ndarray | None) -> bytes:
    buffer = io.BytesIO()
    arrays = {}
    if keypoints is not None:
        arrays["keypoints"] = np.asarray(keypoints, np.float64)
    if mask is not None:
        arrays["mask"] = np.packbits(np.asarray(mask, bool), axis=None)
        arrays["mask_shape"] = np.asarray(mask.shape, np.int64)
    np.savez_compressed(buffer, **arrays)
    return buffer.getvalue()


def _read(path: Path, shape: tuple[int, int]) -> tuple[np.ndarray | None, np.ndarray | None] | None:
    """A kept detection, or None when there is none or it cannot be read (no pickles: ``allow_pickle`` off)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            keypoints = data["keypoints"] if "keypoints" in data else None
            mask = None
            if "mask" in data:
                mask_shape = tuple(int(v) for v in data["mask_shape"])
                if mask_shape != tuple(shape):
                    return None
                mask = np.unpackbits(data["mask"], count=int(np.prod(mask_shape))).reshape(mask_shape).astype(bool)
    except (OSError, ValueError, KeyError, EOFError):
        return None
    if keypoints is not None and keypoints.ndim != 2:
        return None
    return keypoints, mask
