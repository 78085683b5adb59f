"""The ChArUco board definition shared by detection (``charuco``) and the synthetic shots that print it."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, fields
from pathlib import Path

import cv2


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: squares along x / y, square and marker side (metres), ArUco dictionary name."""

    squares_x: int = 8
    squares_y: int = 6
    square_length: float = 0.12
    marker_length: float = 0.09
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self):
        for name in ("squares_x", "squares_y"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not 2 <= value <= 100:
                raise ValueError(f"board {name}: expected a whole number of squares in [2, 100], got {value!r}")
        for name in ("square_length", "marker_length"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not (math.isfinite(value) and 0 < value < 10)
            ):
                raise ValueError(f"board {name}: expected a side in metres in (0, 10), got {value!r}")
        if self.marker_length >= self.square_length:
            raise ValueError(
                f"board marker_length {self.marker_length} must be smaller than square_length {self.square_length}"
            )
        if (
            not isinstance(self.dictionary, str)
            or not self.dictionary.startswith("DICT_")
            or not hasattr(cv2.aruco, self.dictionary)
        ):
            raise ValueError(f"board dictionary: unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_5X5_100)")

    def board(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_length, self.marker_length, dictionary
        )

    @property
    def size(self) -> tuple[float, float]:
        return self.squares_x * self.square_length, self.squares_y * self.square_length


def read_board_json(path: Path) -> dict:
    """The settings of a ``board.json``: a JSON object whose keys are ``BoardSpec`` fields (each checked when the
    spec is built), besides the ``reference_shot`` and ``cameras`` that narf-synth records for information.

    Raises:
        ValueError: not JSON, not an object, or a key that is not a board setting, naming the file.
    """
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a board definition ({err})") from None
    known = [f.name for f in fields(BoardSpec)]
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object with keys among {', '.join(known)}")
    unknown = sorted(set(data) - set(known) - {"reference_shot", "cameras"})
    if unknown:
        raise ValueError(f"{path}: unknown key(s) {unknown}; a board has {', '.join(known)}")
    return {k: v for k, v in data.items() if k in known}
