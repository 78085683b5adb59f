"""A picture for the docs from current fits: ``python -m bench.figure_side_by_side OUT.jpg RUN [RUN ...]``.

Each run is evaluated on a copy (its own report stays as it is) with ``narf-eval --split SPLIT --limit 1 --grids 1``
for each ``--split`` (default: ``novel_view`` and ``novel_pose``), and the picture puts, for each split, the ground
truth and every run's render side by side, cropped to the person (the ground truth's non-black pixels, padded), one
row a split. ``make docs-images`` makes the docs' pictures with it (docs/results/detail.md).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from fitting.files import write_image


def first_grid(run: Path, split: str, work: Path) -> np.ndarray:
    """The first grid row (ground truth | render | depth | parts | error, BGR) that ``narf-eval --limit 1 --grids 1``
    writes for ``split`` on a copy of ``run`` in ``work`` (the run's own report stays as it is)."""
    copy = work / run.name
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("eval", "val", "videos"))
    command = [str(Path(sys.executable).with_name("narf-eval")), "--run", str(copy), "--split", split]
    subprocess.run([*command, "--limit", "1", "--grids", "1", "--quiet"], check=True, stdout=subprocess.DEVNULL)
    grids = sorted((copy / "eval" / "grids" / split).glob("*.png"))
    if not grids:
        raise SystemExit(f"{run}: narf-eval wrote no {split} grid")
    return cv2.imread(str(grids[0]))


def _grid_tiles(run: Path, split: str, work: Path) -> tuple[np.ndarray, np.ndarray]:
    """(ground truth, render) of :func:`first_grid`."""
    image = first_grid(run, split, work)
    width = _tile_width(image)
    return image[:, :width], image[:, width : 2 * width]


def _tile_width(image: np.ndarray) -> int:
    """The width of one tile of a grid row (ground truth | render | depth | parts | error: five equal tiles)."""
    return image.shape[1] // 5


def _crop(tiles: list[np.ndarray], pad: int = 12) -> list[np.ndarray]:
    """The tiles cut to the ground truth's non-black pixels (the person on the evaluation's black background)."""
    rows, cols = np.nonzero(tiles[0].max(-1) > 8)
    if len(rows) == 0:
        return tiles
    top, bottom = max(rows.min() - pad, 0), rows.max() + pad + 1
    left, right = max(cols.min() - pad, 0), cols.max() + pad + 1
    return [t[top:bottom, left:right] for t in tiles]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.figure_side_by_side", description=__doc__)
    parser.add_argument("out", type=Path, help="the picture (.jpg or .png)")
    parser.add_argument("runs", type=Path, nargs="+", help="fitted runs (narf-fit --out), rendered left to right")
    parser.add_argument("--split", action="append", help="splits, one row each (default: novel_view, novel_pose)")
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for split in args.split or ["novel_view", "novel_pose"]:
            tiles = [_grid_tiles(run, split, Path(work)) for run in args.runs]
            rows.append(np.concatenate(_crop([tiles[0][0], *(render for _, render in tiles)]), axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
    write_image(args.out, np.concatenate(rows, axis=0), (cv2.IMWRITE_JPEG_QUALITY, 90))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
