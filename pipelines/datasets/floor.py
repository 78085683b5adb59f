"""The floor of a capture: found by ``narf-prepare-capture`` from the fitted feet, or given (``--floor``), written as
``floor.json`` (docs/formats.md §1.10).

The floor is the plane {x : x . up = height} of the calibration's world. Found from the feet, ``up`` is the
cameras' mean up axis (the mean of their -R[1, :] rows: cameras stand upright) and ``height`` the median over
frames of the fitted body's lowest point along it: a foot is on the floor in most frames of a walk or a dance, so
the frames in the air and a few sunk feet move the median little. Given, it is a world axis and the floor's
coordinate on it (``z-down=0``: z points down and the floor is z = 0)."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipelines.datasets.errors import CaptureError

_GIVEN = re.compile(r"^([xyz])-(up|down)(?:=(.+))?$")


@dataclass(frozen=True)
class Floor:
    """The plane {x : x . up = height}: ``up`` (3,) unit, ``height`` in metres; ``source`` "feet" or "given"."""

    up: np.ndarray
    height: float
    source: str

    def to_json(self) -> dict:
        return {"up": [float(v) for v in self.up], "height": float(self.height), "source": self.source}


def parse_floor(text: str) -> Floor | None:
    """``auto`` -> None (find it from the feet); ``z-up``, ``y-down=0.02``, ...: which world axis points up (or
    down) and the floor's coordinate on that axis (0 when left out).

    Raises:
        ValueError: anything else, with what is expected.
    """
    if text.strip().lower() == "auto":
        return None
    match = _GIVEN.match(text.strip().lower())
    try:
        coordinate = float(match.group(3) or "0") if match else None
    except ValueError:
        coordinate = None
    if coordinate is None or not np.isfinite(coordinate):
        raise ValueError(
            f"expected 'auto', or AXIS-up / AXIS-down[=COORD] such as 'z-up' or 'y-down=0.02'; got '{text}'"
        )
    sign = 1.0 if match.group(2) == "up" else -1.0
    up = np.zeros(3)
    up["xyz".index(match.group(1))] = sign
    return Floor(up, sign * coordinate, "given")


def camera_up(cameras) -> np.ndarray:
    """World up as the normalised mean of the cameras' -R[1, :] rows (image rows point down in upright cameras)."""
    up = -np.mean([c.cam_from_world[1, :3] for c in cameras], axis=0)
    return up / np.linalg.norm(up)


def _lowest(vertices: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(F,) each frame's lowest point along ``up``: ``vertices`` (F, V, 3)."""
    return (vertices @ up).min(axis=1)


def floor_from_feet(vertices: np.ndarray, up: np.ndarray) -> Floor:
    """The floor under fitted bodies (module docstring). ``vertices`` (F, V, 3) world; ``up`` (3,) unit."""
    return Floor(np.asarray(up, np.float64), float(np.median(_lowest(vertices, up))), "feet")


def feet_against_floor(vertices: np.ndarray, floor: Floor) -> dict:
    """How the fitted feet meet the floor, in cm: each frame's lowest point above it (negative: below), its median
    and the lowest frame's."""
    clearance = 100 * (_lowest(vertices, floor.up) - floor.height)
    return {"lowest_point_cm_median": float(np.median(clearance)), "lowest_point_cm_min": float(clearance.min())}


def write_floor(root: Path, floor: Floor) -> None:
    (Path(root) / "floor.json").write_text(json.dumps(floor.to_json(), indent=1))


def read_floor(path: Path) -> Floor:
    """A ``floor.json``, checked: ``up`` three finite numbers, not all zero (normalised), ``height`` finite."""
    try:
        data = json.loads(Path(path).read_text())
        up = np.asarray(data["up"], np.float64)
        height = float(data["height"])
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CaptureError(f"{path}: not a floor file ({err})") from None
    except (KeyError, TypeError, ValueError) as err:
        raise CaptureError(f"{path}: expected {{'up': [x, y, z], 'height': h}} ({type(err).__name__}: {err})") from None
    if up.shape != (3,) or not np.isfinite(up).all() or np.linalg.norm(up) < 1e-9 or not np.isfinite(height):
        raise CaptureError(f"{path}: 'up' must be 3 finite numbers, not all zero, and 'height' finite")
    return Floor(up / np.linalg.norm(up), height, str(data.get("source", "given")))
