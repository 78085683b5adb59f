"""``narf-export-mesh``: the fitted body as a mesh (PLY, OBJ or glTF binary) at a capture frame or along a motion."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.common import HelpFormatter, at_least, run_cli


def frame_window(text: str) -> tuple[int, int]:
    """'A:B' -> (A, B), B excluded."""
    first, sep, last = text.partition(":")
    if not sep or not first.isdigit() or not last.isdigit() or int(last) <= int(first):
        raise argparse.ArgumentTypeError(f"expected A:B with 0 <= A < B (frames A..B-1), got '{text}'")
    return int(first), int(last)


def main(argv: list[str] | None = None) -> int:
    from fitting.trainer import auto_device
    from pipelines.runs.kinds import kind_of_run
    from pipelines.runs.requests import a_run

    parser = argparse.ArgumentParser(
        prog="narf-export-mesh",
        description="Extract the surface of a fitted avatar's density field (scikit-image marching cubes over the "
        "union of the posed part boxes) with vertex colours from the colour branch (seen from outside along the "
        "normal) and a per-vertex part index, in the capture's world (metres). PLY stores the part as a 'part' "
        "vertex property, glTF binary as '_PART', OBJ in <stem>_parts.txt beside the mesh. With --motion, one file "
        "per frame: <stem>_<frame>.<ext>, the motion placed as narf-render-video places it.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--run", type=Path, required=True, help="run folder written by narf-fit --out")
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--frame", type=int, help="a frame of the fitted capture (its SMPL parameters)")
    which.add_argument("--motion", type=Path, help="an AMASS .npz, ZJU params/ folder or SURREAL _info.mat")
    parser.add_argument("--frames", type=frame_window, default=None, help="--motion: frames A:B (B excluded)")
    parser.add_argument("--out", type=Path, required=True, help="output .ply, .obj or .glb")
    parser.add_argument("--resolution", type=at_least(8), default=256, help="grid samples along the longest side")
    parser.add_argument(
        "--level",
        type=float,
        default=None,
        help="density iso-level (1/m); default: the level whose silhouettes best match the fit's own training masks "
        "(4 training frames x up to 4 training cameras; docs/design.md, Meshes out)",
    )
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    if args.frames is not None and args.motion is None:
        raise ValueError("--frames A:B picks frames of a --motion; use --frame N for a capture frame")
    if not args.run.is_dir():
        raise FileNotFoundError(f"{args.run}: no such run folder")
    kind = kind_of_run(args.run)
    if kind.export is None:
        raise ValueError(f"{args.run}: {a_run(kind.name)}; narf-export-mesh exports subject runs")
    written, level = kind.export(
        args.run,
        args.out,
        args.frame,
        args.motion,
        args.frames,
        args.resolution,
        args.level,
        str(auto_device(args.device)),
        not args.quiet,
    )
    if level["level_source"] != "given":
        print(f"narf-export-mesh: level {level['level']:.3g} (silhouette IoU {level['level_iou']:.3f} on {level['level_views']} training views)")
    print(f"narf-export-mesh: wrote {written[0]}" + (f" ... ({len(written)} files)" if len(written) > 1 else ""))
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-export-mesh", main))
