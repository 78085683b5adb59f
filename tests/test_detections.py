"""The detection cache of narf-prepare-capture (pipelines/prepare/sources/detections.py): each view detected once,
across a killed run, a rerun and a replacement, with the same capture written."""

import hashlib
import json

import cv2
import numpy as np
import pytest

from pipelines.prepare.sources.detections import CachedDetector, detections_folder
from pipelines.prepare.sources.recordings import Source, find_sources, read_frames


class Counting:
    """A detector that answers from a table (image hash -> (keypoints, mask)) and counts its calls; ``fail_after``
    calls, it raises KeyboardInterrupt, as a kill in the middle of the detection stage would end the run."""

    def __init__(self, table: dict, fail_after: int | None = None):
        self.table, self.calls, self.fail_after = table, 0, fail_after

    def __call__(self, rgb: np.ndarray):
        if self.fail_after is not None and self.calls >= self.fail_after:
            raise KeyboardInterrupt
        self.calls += 1
        return self.table[hashlib.sha256(rgb.tobytes()).hexdigest()]


def test_a_view_is_detected_once_and_read_back_exactly(tmp_path):
    """A second look at the same view reads the kept keypoints and mask back bit for bit; another image size or
    another detector misses; a damaged file is detected again."""
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (40, 30, 3), dtype=np.uint8)
    keypoints, mask = rng.normal(size=(33, 3)), rng.random((40, 30)) > 0.5
    video = tmp_path / "cam.mp4"
    video.write_bytes(b"not read")
    source = Source("cam", video, True)
    detector = Counting({hashlib.sha256(rgb.tobytes()).hexdigest(): (keypoints, mask)})
    cache = CachedDetector(detector, tmp_path / "cache", "fake|1")
    for _ in range(2):
        found = cache(source, 7, rgb)
        assert np.array_equal(found[0], keypoints) and np.array_equal(found[1], mask)
    assert (cache.detected, cache.reused, detector.calls) == (1, 1, 1)
    assert cache.path(source, 7, rgb.shape) != cache.path(source, 7, (20, 15, 3))
    other = CachedDetector(detector, tmp_path / "cache", "fake|2")
    assert other.path(source, 7, rgb.shape) != cache.path(source, 7, rgb.shape)
    cache.path(source, 7, rgb.shape).write_bytes(b"cut short")
    assert np.array_equal(cache(source, 7, rgb)[1], mask) and detector.calls == 2
    nobody = Counting({hashlib.sha256(rgb.tobytes()).hexdigest(): (None, None)})
    empty = CachedDetector(nobody, tmp_path / "cache2", "fake|1")
    assert empty(source, 1, rgb) == (None, None) and empty(source, 1, rgb) == (None, None) and nobody.calls == 1


def test_a_finished_prepare_keeps_only_the_detections_it_used(tmp_path):
    """Two runs of one take at two resolutions (the images resized), each with a crop: the second run's prune leaves
    its own set only, and the size it reports is that set's. (Checked against no prune: both sets stayed.)"""
    rng = np.random.default_rng(1)
    video = tmp_path / "cam.mp4"
    video.write_bytes(b"not read")
    source = Source("cam", video, True)
    sizes = {}
    for rows in (40, 20):
        images = [rng.integers(0, 255, (rows, 30, 3), dtype=np.uint8) for _ in range(3)]
        table = {hashlib.sha256(im.tobytes()).hexdigest(): (None, np.ones(im.shape[:2], bool)) for im in images}
        crop = images[0][: rows // 2]
        table[hashlib.sha256(np.ascontiguousarray(crop).tobytes()).hexdigest()] = (None, np.ones(crop.shape[:2], bool))
        cache = CachedDetector(Counting(table), tmp_path / "cache", "fake|1")
        for frame, image in enumerate(images):
            cache(source, frame, image)
        cache.crop(crop, (0, 0, 30, rows // 2))
        sizes[rows] = cache.used_size()
    assert len(list((tmp_path / "cache").rglob("*.npz"))) == 8  # two full sets before the prune
    assert cache.prune() == 4
    kept = sorted((tmp_path / "cache").rglob("*.npz"))
    assert set(kept) == cache.used and sizes[20] == (4, sum(p.stat().st_size for p in kept))


@pytest.fixture()
def segmenter(recording):
    """The recording's true masks, keyed by the decoded image each view gives the detector."""
    rec = recording / "rec"
    table = {}
    for source in find_sources(rec):
        files = sorted((rec / "masks" / source.name).iterdir())
        for (_, bgr), path in zip(read_frames(source, range(10**9)), files):
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            table[hashlib.sha256(rgb.tobytes()).hexdigest()] = (None, cv2.imread(str(path), 0) > 0)
    return table


@pytest.mark.slow
def test_a_killed_prepare_reuses_its_detections_and_writes_the_same_capture(
    recording, segmenter, tmp_path, monkeypatch
):
    """The segmenter killed after 15 of the 40 views: nothing is published, the 15 are kept; the rerun detects the
    other 25 only, and a replacement (--overwrite) detects none; both keep the same frames and fit the same bodies,
    to the bit: the masks are the same bits either way (the first test), the mask's distance transform is the same
    bits on every call (``distance_to_mask``; OpenCV's own was not, which made these figures 3-5 % apart), and one
    process keeps its thread count (docs/results/faults.md)."""
    import pipelines.prepare.sources.detect as detect
    from pipelines.cli import prepare_capture
    from pipelines.cli.common import run_cli

    rec, out = recording / "rec", tmp_path / "out"
    detectors = []

    def make(*_):
        detectors.append(Counting(segmenter, fail_after=15 if not detectors else None))
        return detectors[-1]

    monkeypatch.setattr(detect, "BlazePose", make)
    monkeypatch.setattr(detect, "detector_id", lambda *_: "the true masks")
    # a short body fit: the detections and the bits of the bodies are tested, not how well they fit
    short = ["--fit-iterations", "100", "--silhouette-iterations", "50", "--quiet"]
    argv = [str(rec), "--out", str(out), "--keypoints", str(rec / "keypoints"), *short]
    assert run_cli("narf-prepare-capture", prepare_capture.main, argv) == 130
    assert not out.exists() and detectors[0].calls == 15
    assert run_cli("narf-prepare-capture", prepare_capture.main, argv) == 0
    first = json.loads((out / "report.json").read_text())
    assert first["detections"]["reused"] == 15 and first["detections"]["detected"] == 25 == detectors[1].calls
    assert run_cli("narf-prepare-capture", prepare_capture.main, [*argv, "--overwrite"]) == 0
    second = json.loads((out / "report.json").read_text())
    assert second["detections"]["reused"] == 40 and detectors[2].calls == 0
    assert first["frames"] == second["frames"]
    assert first["summary"] == second["summary"]
    assert detections_folder(out).is_dir()
