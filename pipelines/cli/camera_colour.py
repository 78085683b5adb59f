"""``narf-camera-colour``: measure each camera's colour gain of a capture on its floor and write ``colour.json``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.common import HelpFormatter, run_cli


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="narf-camera-colour",
        formatter_class=HelpFormatter,
        description="Measure each camera's colour gain (white balance and exposure, per R/G/B channel) of a "
        "ZJU-MoCap-layout capture on its floor, and write CAPTURE/colour.json (docs/formats.md §1.12), which "
        "narf-fit and narf-eval then use (docs/model.md §6). narf-prepare-capture does this for the captures it "
        "writes; this command is for captures prepared before, or any capture with a floor.json, masks and "
        "vertices/. Each camera's background is the median of --frames frames with the person left out; the "
        "cameras are compared at points of the floor around the bodies.",
    )
    parser.add_argument("capture", type=Path, help="the capture folder (annots.npy, floor.json, mask/, vertices/)")
    parser.add_argument("--frames", type=int, default=20, help="frames spread over the take whose median is used")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing colour.json")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.frames < 3:
        raise ValueError(f"--frames must be at least 3 (a median of fewer is not a background), got {args.frames}")
    from fitting.files import folder_lock
    from pipelines.prepare.layout.colour import colour_summary, write_capture_colour

    target = args.capture / "colour.json"
    with folder_lock(args.capture):  # the capture's writer: not into a folder narf-prepare-capture is replacing
        if target.exists() and not args.overwrite:
            raise FileExistsError(f"{target}: exists (--overwrite replaces it)")
        colour = write_capture_colour(args.capture, args.frames, progress=not args.quiet)
    print(f"narf-camera-colour: {colour_summary(colour)}; wrote {target}")
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-camera-colour", main))
