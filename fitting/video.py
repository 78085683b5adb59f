"""Video frames and H.264 mp4 writing (imageio-ffmpeg). What to render is ``pipelines.runs.subject.video``."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import imageio.v2 as imageio
import numpy as np

from fitting.files import atomic_output
from fitting.plots import colour_depth, colour_segmentation


def video_frame(render: dict) -> np.ndarray:
    """RGB | depth | part segmentation side by side, uint8."""
    tiles = [render["rgb"], colour_depth(render["depth"], render["mask"])]
    if "segmentation" in render:
        tiles.append(colour_segmentation(render["segmentation"]))
    return (np.clip(np.concatenate(tiles, axis=1), 0, 1) * 255 + 0.5).astype(np.uint8)


def write_mp4(out: Path, frames: Iterable[np.ndarray], fps: int) -> Path:
    """H.264 mp4 through imageio-ffmpeg, written to a temporary file and renamed when complete. ``frames`` may be a
    generator: each frame is encoded as it comes (nothing is held for the whole video)."""
    out = Path(out)
    frames = iter(frames)
    first = next(frames, None)
    if first is None:
        raise ValueError(f"{out}: no frames to write")
    if out.exists() and out.is_dir():
        raise IsADirectoryError(f"{out}: is a folder; give a .mp4 file name")
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(out) as tmp:
        with imageio.get_writer(
            tmp,
            fps=fps,
            codec="libx264",
            quality=8,
            macro_block_size=1,
            pixelformat="yuv420p" if all(s % 2 == 0 for s in first.shape[:2]) else None,
        ) as w:
            w.append_data(first)
            for frame in frames:
                w.append_data(frame)
    return out
