"""Training views on disk: each view's pixels inside its sampling box, as uint8, in one anonymous file written
once; a training step reads back only the views it draws, so memory does not grow with the number of views
(docs/design.md *Training views on disk*).

A record is the crop's RGB (h, w, 3) followed by its label map (h, w): the sampling pool of each pixel in the low
two bits (``POOL_BODY``, ``POOL_BORDER``, ``POOL_BACKGROUND``; 0 outside every pool) and ``BAND_BIT`` on the
5-px boundary band that the mask loss skips. Pixels of unknown owner (somebody else in front of the person,
docs/formats.md §1.5) are in no pool, so no ray is drawn there, and carry ``BAND_BIT``."""

from __future__ import annotations

import errno
import os
import tempfile
from pathlib import Path

import cv2
import numpy as np

from fitting.files import named_errors

BORDER_PX = 11  # side of the square dilation kernel: the border pool is the 5-px ring around the silhouette
BOX_PAD = 0.1  # the sampling box: the dilated silhouette's bounding box grown by 10 % of its size on each side
POOL_BODY, POOL_BORDER, POOL_BACKGROUND = 1, 2, 3
POOL_BITS = 3
BAND_BIT = 4


def sampling_labels(
    mask: np.ndarray, band: np.ndarray, unknown: np.ndarray | None = None
) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """Pool labels of one view and its sampling box.

    Body = the silhouette; border = the dilation ring (``BORDER_PX``) outside it; background = the rest of the box,
    which is the dilated silhouette's bounding box padded by ``BOX_PAD`` of its size (the whole image when the
    silhouette is empty: then every pixel is background).

    Args:
        mask: (H, W) bool silhouette.
        band: (H, W) bool boundary band (mask loss weight 0).
        unknown: (H, W) bool pixels of unknown owner (no pool, ``BAND_BIT``), or None.

    Returns:
        labels (H, W) uint8, and the box (y0, y1, x0, x1), end-exclusive.
    """
    height, width = mask.shape
    dilated = cv2.dilate(mask.astype(np.uint8), np.ones((BORDER_PX, BORDER_PX), np.uint8)) > 0
    y0, y1, x0, x1 = 0, height, 0, width
    if dilated.any():
        ys, xs = np.nonzero(dilated)
        pad_y, pad_x = int(BOX_PAD * (ys.max() - ys.min() + 1)), int(BOX_PAD * (xs.max() - xs.min() + 1))
        y0, y1 = int(max(ys.min() - pad_y, 0)), int(min(ys.max() + pad_y + 1, height))
        x0, x1 = int(max(xs.min() - pad_x, 0)), int(min(xs.max() + pad_x + 1, width))
    labels = np.zeros((height, width), np.uint8)
    labels[y0:y1, x0:x1] = POOL_BACKGROUND
    labels[dilated] = POOL_BORDER
    labels[mask] = POOL_BODY
    labels[band] |= BAND_BIT
    if unknown is not None:
        labels[unknown] = BAND_BIT
    return labels, (y0, y1, x0, x1)


class ViewStore:
    """Cropped views in an anonymous file under ``directory`` (the system's temporary folder by default): removed
    by the operating system when the store is garbage-collected or the process ends, however it ends.

    Outside its box a view must be one colour (the composited background) to be stored cropped; otherwise the
    whole view is stored, so ``full`` always gives back exactly what was added."""

    def __init__(self, directory: str | Path | None = None):
        if directory is not None:
            Path(directory).mkdir(parents=True, exist_ok=True)
        self._where = Path(directory if directory is not None else tempfile.gettempdir())
        with named_errors(self._where):
            self._file = tempfile.TemporaryFile(prefix="narf-views-", dir=directory)
        self._end = 0
        self._records: list[tuple[int, int, int, int, int, int, int]] = []  # offset, y0, x0, h, w, H, W
        self._fill: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._records)

    def add(self, image: np.ndarray, mask: np.ndarray, band: np.ndarray, unknown: np.ndarray | None = None) -> None:
        """Store a view: ``image`` (H, W, 3) uint8, ``mask``, ``band`` and ``unknown`` (or None) (H, W) bool."""
        height, width = mask.shape
        if image.shape != (height, width, 3) or image.dtype != np.uint8 or band.shape != mask.shape:
            raise ValueError(f"a view needs image (H, W, 3) uint8 and mask, band (H, W); got {image.shape}")
        labels, (y0, y1, x0, x1) = sampling_labels(mask, band, unknown)
        fill = image[0, 0] if y0 > 0 or x0 > 0 else image[-1, -1]
        outside = (image[:y0], image[y1:], image[y0:y1, :x0], image[y0:y1, x1:])
        if any((part != fill).any() for part in outside):
            y0, y1, x0, x1 = 0, height, 0, width  # not one colour outside the box: keep the whole view
        crop = np.ascontiguousarray(image[y0:y1, x0:x1])
        record = crop.tobytes() + np.ascontiguousarray(labels[y0:y1, x0:x1]).tobytes()
        self._write(record)
        self._records.append((self._end, y0, x0, y1 - y0, x1 - x0, height, width))
        self._fill.append(fill.copy())
        self._end += len(record)

    def _write(self, record: bytes) -> None:
        """Append ``record`` at the end of the store; a full disk (an error, or a write that stops short) ends in an
        OSError naming the store's folder."""
        done = 0
        with named_errors(self._where / "(the training views' store)"):
            while done < len(record):
                written = os.pwrite(self._file.fileno(), record[done:], self._end + done)
                if written == 0:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                done += written

    def box(self, index: int) -> tuple[int, int, int, int]:
        """(y0, x0, h, w) of view ``index``'s stored crop."""
        return self._records[index][1:5]

    def size(self, index: int) -> tuple[int, int]:
        """(H, W) of view ``index``."""
        return self._records[index][5:7]

    def read(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """RGB (h, w, 3) uint8 and labels (h, w) uint8 of view ``index``'s crop (``box``), read from the file."""
        offset, _, _, h, w, _, _ = self._records[index]
        data = os.pread(self._file.fileno(), 4 * h * w, offset)
        if len(data) != 4 * h * w:
            raise OSError(f"training view store: view {index} is truncated ({len(data)} of {4 * h * w} bytes)")
        raw = np.frombuffer(data, np.uint8)
        return raw[: 3 * h * w].reshape(h, w, 3), raw[3 * h * w :].reshape(h, w)

    def _full_labels(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """View ``index``'s stored crop (h, w, 3) and its labels at full size (H, W), 0 outside the crop."""
        rgb, labels = self.read(index)
        y0, x0, h, w = self.box(index)
        full_labels = np.zeros(self.size(index), np.uint8)
        full_labels[y0 : y0 + h, x0 : x0 + w] = labels
        return rgb, full_labels

    def mask_and_unknown(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """View ``index``'s mask and its pixels of unknown owner (in no pool, with ``BAND_BIT``), (H, W) bool each,
        as added; one read of the store."""
        _, labels = self._full_labels(index)
        return (labels & POOL_BITS) == POOL_BODY, (labels & (POOL_BITS | BAND_BIT)) == BAND_BIT

    def full(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """View ``index`` as it was added: image (H, W, 3) uint8, mask and band (H, W) bool."""
        rgb, labels = self._full_labels(index)
        y0, x0, h, w = self.box(index)
        image = np.empty((*labels.shape, 3), np.uint8)
        image[:] = self._fill[index]
        image[y0 : y0 + h, x0 : x0 + w] = rgb
        return image, (labels & POOL_BITS) == POOL_BODY, (labels & BAND_BIT) > 0
