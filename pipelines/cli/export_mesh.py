"""``narf-export-mesh``: the fitted body as a mesh (PLY, OBJ or glTF binary) at a capture frame or along a motion."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.common import (
    HelpFormatter,
    add_motion_fps,
    add_smpl_dir,
    at_least,
    attach_dash_values,
    own_context,
    positive_number,
    run_cli,
    use_smpl_dir,
)


def frame_window(text: str) -> tuple[int, int]:
    """'A:B' -> (A, B), B excluded."""
    first, sep, last = text.partition(":")
    if not sep or not first.isdigit() or not last.isdigit() or int(last) <= int(first):
        raise argparse.ArgumentTypeError(f"expected A:B with 0 <= A < B (frames A..B-1), got '{text}'")
    return int(first), int(last)


def _print_level(record: dict) -> None:
    if record["level_source"] != "given":
        iou, views = record["level_iou"], record["level_views"]
        print(f"narf-export-mesh: level {record['level']:.3g} (silhouette IoU {iou:.3f} on {views} training views)")


def build_parser() -> argparse.ArgumentParser:
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
    which = parser.add_mutually_exclusive_group()
    which.add_argument(
        "--frame", type=int, help="a frame of the fitted capture (its SMPL parameters); --rigged: the bind pose"
    )
    which.add_argument(
        "--motion", type=Path, help="an AMASS .npz, ZJU params/ folder or SURREAL _info.mat; --rigged: the animation"
    )
    parser.add_argument("--frames", type=frame_window, default=None, help="--motion: frames A:B (B excluded)")
    parser.add_argument("--out", type=Path, required=True, help="output .ply, .obj or .glb (--rigged: .glb)")
    parser.add_argument(
        "--rigged",
        action="store_true",
        help="one skinned glTF binary: the mesh in the rest pose (or --frame's), the body model's 24 named joints as "
        "its skeleton, skin weights from NARF's part selector, --motion baked as an animation; y-up, floor at y = 0",
    )
    parser.add_argument(
        "--skin",
        choices=("selector", "rigid"),
        default="selector",
        help="--rigged: a vertex follows the selector's 4 most probable parts, or its most probable part alone",
    )
    parser.add_argument("--fps", type=float, default=None, help="--rigged --motion: frame rate (default: the motion's)")
    add_motion_fps(parser, "--rigged --motion")
    parser.add_argument("--resolution", type=at_least(8), default=256, help="grid samples along the longest side")
    parser.add_argument(
        "--level",
        type=positive_number,
        default=None,
        help="density iso-level (1/m); default: the level whose silhouettes best match the fit's own training masks "
        "(4 training frames x up to 4 training cameras; docs/design.md, Meshes out)",
    )
    add_smpl_dir(parser)
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


@own_context
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(attach_dash_values(argv, ("--frames",)))
    from fitting.files import folder_lock
    from fitting.run_folder import auto_device
    from pipelines.runs.kinds import open_run
    from pipelines.runs.requests import ExportRequest, a_run

    use_smpl_dir(args.smpl_dir)
    _check_flags(args)
    kind, run = open_run(args.run)
    if kind.export is None:
        raise ValueError(f"{args.run}: {a_run(kind.name)}; narf-export-mesh exports subject runs")
    request = ExportRequest(
        out=Path(args.out),
        frame=args.frame,
        motion=args.motion,
        window=args.frames,
        resolution=args.resolution,
        level=args.level,
        rigged=args.rigged,
        skin=args.skin,
        fps=args.fps,
        motion_fps=args.motion_fps,
        device=str(auto_device(args.device)),
        progress=not args.quiet,
    )
    with folder_lock(Path(args.out)):  # one writer per output
        return _export(kind, run, request, args)


def _export(kind, run, request, args) -> int:
    """Write the rigged glTF or the meshes and say what was written."""
    from pipelines.runs.requests import a_run

    if args.rigged:
        if kind.rigged is None:
            raise ValueError(f"{args.run}: {a_run(kind.name)}; narf-export-mesh --rigged exports subject runs")
        path, record = kind.rigged(run, request)
        _print_level(record)
        frames = f", {record['frames']} animation frames" if record["frames"] else ""
        print(f"narf-export-mesh: wrote {path} (24 joints, {record['vertices']} vertices{frames})")
        return 0
    written, level = kind.export(run, request)
    _print_level(level)
    print(f"narf-export-mesh: wrote {written[0]}" + (f" ... ({len(written)} files)" if len(written) > 1 else ""))
    return 0


def _check_flags(args) -> None:
    """The flags that contradict each other, an --out that is a folder and a missing run, before any work."""
    if args.fps is not None and not (args.fps > 0 and args.fps <= 1000):
        raise ValueError(f"--fps must be in (0, 1000], got {args.fps:g}")
    if (args.fps, args.motion_fps) != (None, None) and not (args.rigged and args.motion is not None):
        raise ValueError("--fps and --motion-fps set the animation's rates of --rigged --motion FILE")
    if not args.rigged and args.frame is None and args.motion is None:
        raise ValueError("one of --frame N or --motion FILE is required (or --rigged for the rest pose)")
    if args.frames is not None and args.motion is None:
        raise ValueError("--frames A:B picks frames of a --motion; use --frame N for a capture frame")
    if Path(args.out).is_dir():  # checked before the work, not when the file is put in place
        raise ValueError(
            f"{args.out}: is a folder; --out names the mesh file to write (e.g. {Path(args.out) / 'body.ply'})"
        )
    if not args.run.is_dir():
        raise FileNotFoundError(f"{args.run}: no such run folder")


def entrypoint() -> None:
    sys.exit(run_cli("narf-export-mesh", main))
