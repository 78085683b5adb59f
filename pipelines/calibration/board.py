"""The ChArUco board definition shared by detection (``charuco``) and the synthetic shots that print it."""

from __future__ import annotations

from dataclasses import dataclass

import cv2


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: squares along x / y, square and marker side (metres), ArUco dictionary name."""

    squares_x: int = 8
    squares_y: int = 6
    square_length: float = 0.12
    marker_length: float = 0.09
    dictionary: str = "DICT_5X5_100"

    def board(self) -> cv2.aruco.CharucoBoard:
        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary '{self.dictionary}'")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_length, self.marker_length, dictionary
        )

    @property
    def size(self) -> tuple[float, float]:
        return self.squares_x * self.square_length, self.squares_y * self.square_length
