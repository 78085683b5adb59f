"""The docs' pictures from current runs and captures, one kind a call (``make docs-images`` runs them all):

* ``python -m bench.docs_images demo RUN OUT.png``: the first ``novel_pose`` grid that ``narf-eval --grids 1`` writes
  for ``RUN`` (ground truth | render | depth | parts | error), evaluated on a copy so the run's report stays;
* ``python -m bench.docs_images overlay CAPTURE OUT.jpg [--frame 50]``: that frame of every camera's ``overlay/``
  (the fitted body and keypoints over the recording, as ``narf-prepare-capture`` draws them) side by side.

The picture of the real demo's held-out camera is ``bench.figure_side_by_side``'s.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import cv2
import numpy as np

from bench.figure_side_by_side import first_grid
from fitting.files import write_image

#: rows of the overlay picture
OVERLAY_HEIGHT = 480


def demo_grid(run: Path, out: Path) -> None:
    """The first ``novel_pose`` grid of ``run`` (``bench.figure_side_by_side.first_grid``) written to ``out``."""
    with tempfile.TemporaryDirectory(prefix="narf-docs-") as work:
        write_image(out, first_grid(run, "novel_pose", Path(work)))


def overlay_row(capture: Path, out: Path, frame: int) -> None:
    """Frame ``frame`` of every camera's overlay in ``capture``, each scaled to ``OVERLAY_HEIGHT`` rows, in a row."""
    folders = sorted(p for p in (capture / "overlay").iterdir() if p.is_dir()) if (capture / "overlay").is_dir() else []
    tiles = []
    for folder in folders:
        image = cv2.imread(str(folder / f"{frame:06d}.jpg"))
        if image is None:
            raise SystemExit(f"bench.docs_images: error: {folder / f'{frame:06d}.jpg'}: missing or unreadable")
        width = round(image.shape[1] * OVERLAY_HEIGHT / image.shape[0])
        tiles.append(cv2.resize(image, (width, OVERLAY_HEIGHT), interpolation=cv2.INTER_AREA))
    if not tiles:
        raise SystemExit(f"bench.docs_images: error: {capture}: no overlay/ (prepare it with narf-prepare-capture)")
    write_image(out, np.concatenate(tiles, axis=1), (cv2.IMWRITE_JPEG_QUALITY, 85))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.docs_images", description=__doc__.split("\n\n")[0])
    kinds = parser.add_subparsers(dest="kind", required=True)
    demo = kinds.add_parser("demo", help="a run's first novel_pose grid")
    demo.add_argument("run", type=Path)
    demo.add_argument("out", type=Path)
    overlay = kinds.add_parser("overlay", help="one frame of a capture's overlays, every camera side by side")
    overlay.add_argument("capture", type=Path)
    overlay.add_argument("out", type=Path)
    overlay.add_argument("--frame", type=int, default=50)
    args = parser.parse_args(argv)
    if args.kind == "demo":
        demo_grid(args.run, args.out)
    else:
        overlay_row(args.capture, args.out, args.frame)


if __name__ == "__main__":
    main()
