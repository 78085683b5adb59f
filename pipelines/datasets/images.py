"""Images read strictly: a file cut off before its end is an error, never an image padded with grey.

OpenCV decodes a truncated JPEG or PNG into a full-size image (the missing rows grey or black) and only prints a
libjpeg / libpng warning; a capture with such a file would train on the padding. So the file's own end marker is
checked first: JPEG's end-of-image (FF D9, trailing zero bytes allowed) and PNG's IEND chunk."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pipelines.datasets.errors import CaptureError

JPEG_START, JPEG_END = b"\xff\xd8", b"\xff\xd9"
PNG_START, PNG_END = b"\x89PNG\r\n\x1a\n", b"IEND\xaeB`\x82"


def read_image(path: str | Path, flags: int = cv2.IMREAD_COLOR, what: str = "image") -> np.ndarray:
    """``cv2.imread`` that refuses missing, undecodable and truncated files.

    Raises:
        CaptureError: naming the file and what is wrong with it.
    """
    try:
        data = Path(path).read_bytes()
    except OSError as err:
        raise CaptureError(f"{path}: missing or unreadable {what} ({err.strerror or err})") from None
    if data.startswith(JPEG_START) and not data.rstrip(b"\x00").endswith(JPEG_END):
        raise CaptureError(f"{path}: truncated JPEG (no end-of-image marker): the file was cut off")
    if data.startswith(PNG_START) and not data.endswith(PNG_END):
        raise CaptureError(f"{path}: truncated PNG (no IEND chunk): the file was cut off")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if image is None:
        raise CaptureError(f"{path}: missing or unreadable {what}")
    return image
