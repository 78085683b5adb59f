"""Each camera's colour gain: ``colour.json`` of a capture (docs/formats.md §1.12), measured on the floor by
``pipelines.prepare.layout.colour``.

The gain g_c (3,) of camera c is what its pixels record of a colour the rig's cameras see in common: a pixel of a
Lambertian surface is ``g_c * C`` per channel, and the gains' geometric mean over the cameras is 1, so ``C`` is the
rig's mean look. A fit learns ``C``; its renders for camera c are multiplied by ``g_c`` (docs/model.md §6,
*Measured camera colour*)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from fitting.files import atomic_write_text
from pipelines.datasets.errors import CaptureError

#: gains outside this range are not a camera's white balance or exposure but a measurement gone wrong
GAIN_RANGE = (0.25, 4.0)


def read_camera_colour(path: Path, names: list[str]) -> np.ndarray:
    """(C, 3) float32 gains of the cameras ``names`` (the capture's order) from ``colour.json``.

    Raises:
        CaptureError: the file is not JSON, a camera of the capture is missing or one it lists is not the capture's,
            or a gain is not three finite numbers within ``GAIN_RANGE``; the message names the file.
    """
    try:
        data = json.loads(Path(path).read_text())
        cameras = data["cameras"]
        listed = {str(name): entry["gain"] for name, entry in cameras.items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
        raise CaptureError(f"{path}: not a colour file (cameras: NAME: gain: [r, g, b]): {error}") from None
    unknown = sorted(set(listed) - set(names))
    missing = [name for name in names if name not in listed]
    if unknown or missing:
        raise CaptureError(f"{path}: cameras {unknown or missing} are {'not the capture' if unknown else 'missing'}'s")
    gains = []
    for name in names:
        gain = listed[name]
        ok = isinstance(gain, list) and len(gain) == 3 and all(isinstance(v, (int, float)) for v in gain)
        if not ok or not all(math.isfinite(v) and GAIN_RANGE[0] <= v <= GAIN_RANGE[1] for v in gain):
            raise CaptureError(f"{path}: {name}'s gain must be 3 numbers in {list(GAIN_RANGE)}, got {gain}")
        gains.append(gain)
    return np.asarray(gains, np.float32)


def write_camera_colour(path: Path, names: list[str], measured: dict) -> None:
    """Write ``colour.json``: ``measured`` is ``pipelines.prepare.layout.colour.measure_camera_colour``'s result. Gains
    that :func:`read_camera_colour` would refuse are a ValueError here, before anything is written."""
    gains = np.asarray(measured["gains"], float)
    if not (np.isfinite(gains) & (gains >= GAIN_RANGE[0]) & (gains <= GAIN_RANGE[1])).all():
        raise ValueError(f"{path}: gains outside {list(GAIN_RANGE)} are not written: {gains.round(3).tolist()}")
    cameras = {
        name: {
            "gain": [round(float(v), 5) for v in measured["gains"][i]],
            "floor_points": int(measured["points"][i]),
            "pair_residual": round(float(measured["residual"][i]), 5),
            "measured": bool(measured["measured"][i]),
        }
        for i, name in enumerate(names)
    }
    text = json.dumps({"method": measured["method"], "cameras": cameras}, indent=1)
    atomic_write_text(Path(path), text)
