"""``narf-calibrate``: calibrate a multi-view rig from the ChArUco shots in ``CAPTURE_DIR/calib/<camera>/``."""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict
from pathlib import Path

from pipelines.calibration.board import BoardSpec, read_board_json
from pipelines.cli.common import HelpFormatter, at_least, positive_number, run_cli
from pipelines.datasets.errors import CaptureError


def _board(args, calib: Path) -> BoardSpec:
    values = asdict(BoardSpec())
    source = args.board_json or (calib / "board.json" if (calib / "board.json").is_file() else None)
    if source:
        values.update(read_board_json(Path(source)))
    for key in values:
        if getattr(args, key, None) is not None:
            values[key] = getattr(args, key)
    try:
        return BoardSpec(**values)
    except ValueError as err:
        raise ValueError(f"{source or 'the default board'} with the flags given: {err}") from None


def _corners(text: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) >= 2 for p in parts):
        raise argparse.ArgumentTypeError(f"expected inner corners as COLSxROWS with each >= 2 (e.g. 4x7), got '{text}'")
    return int(parts[0]), int(parts[1])


def checkerboard_intrinsics(args) -> int:
    """``--checkerboard``: per-camera intrinsics from checkerboard shots, written to intrinsics.json (and compared
    with ``--compare``)."""
    from pipelines.calibration.workflow import checkerboard_intrinsics as calibrate

    out = args.out or args.capture
    for line in calibrate(args.capture, args.checkerboard, args.square_length, args.compare, out):
        print(f"narf-calibrate: {line}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="narf-calibrate",
        description="Calibrate every camera of a rig from ChArUco shots in CAPTURE_DIR/calib/<camera>/ (shots with "
        "the same file name show the same board pose in several cameras; optional close-ups of one camera go in "
        "calib/<camera>/intrinsics/): sub-pixel detection, per-camera intrinsics (k1, k2, p1, p2, k3; see --fix), "
        "a graph over shared shots, then one joint bundle adjustment of all cameras and board poses with outlier "
        "corners rejected. The reference shot's board frame is the world (ZJU "
        "convention: board on the floor, z down, metres). Writes annots.npy (T in mm), intri.yml/extri.yml, a "
        "COLMAP text model (colmap/, written by pycolmap: OPENCV, or FULL_OPENCV when k3 is not 0), report.json, "
        "rig.png and residuals.png to --out; only --write-annots "
        "touches the capture's own annots.npy (backed up first).",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("capture", type=Path, help="capture folder holding calib/<camera>/*.jpg")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: CAPTURE_DIR/calibration)")
    parser.add_argument("--board-json", type=Path, default=None, help="board definition (default: calib/board.json)")
    parser.add_argument("--squares-x", type=at_least(2, 100), default=None, help="squares along x (overrides the json)")
    parser.add_argument("--squares-y", type=at_least(2, 100), default=None, help="squares along y")
    parser.add_argument("--square-length", type=positive_number, default=None, help="square side in metres")
    parser.add_argument("--marker-length", type=positive_number, default=None, help="marker side in metres")
    parser.add_argument("--dictionary", default=None, help="ArUco dictionary, e.g. DICT_5X5_100")
    parser.add_argument("--reference-shot", default="000", help="shot whose board defines the world frame")
    parser.add_argument(
        "--fix",
        default="k3",
        help="comma-separated parameter groups held fixed: k3 (= 0), "
        "tangential (p1 = p2 = 0), principal_point (image centre); 'none' frees all",
    )
    parser.add_argument("--write-annots", action="store_true", help="also merge the cams into CAPTURE/annots.npy")
    parser.add_argument(
        "--checkerboard",
        type=_corners,
        default=None,
        metavar="COLSxROWS",
        help="intrinsics only, from checkerboard shots: CAPTURE holds one folder of shots per camera (Pose2Sim's "
        "calibration/intrinsics/int_<camera>_img/); COLSxROWS counts inner corners; --square-length is the square "
        "side in metres; writes intrinsics.json to --out (default: CAPTURE)",
    )
    parser.add_argument(
        "--compare",
        type=Path,
        default=None,
        help="with --checkerboard: a calibration file to compare the intrinsics with",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not args.capture.is_dir():
        raise CaptureError(f"{args.capture}: no such capture folder")
    if args.checkerboard:
        return checkerboard_intrinsics(args)
    from pipelines.calibration.workflow import calibrate_capture, fixed_groups, merge_into_capture, write_outputs

    spec = _board(args, args.capture / "calib")
    fixed = fixed_groups(args.fix)
    out = args.out or args.capture / "calibration"
    if out.exists() and not out.is_dir():  # checked before the calibration, not after
        raise FileExistsError(f"{out}: exists and is not a folder")
    from fitting.files import folder_lock, restore_merged

    with folder_lock(out):  # a calibration killed while it moved its folders in: colmap/ back before anything else
        restore_merged(out)
    cameras, ims, report, figures = calibrate_capture(args.capture, spec, args.reference_shot, not args.quiet, fixed)
    write_outputs(out, cameras, ims, report, figures)
    worst = max(report["cameras"].items(), key=lambda kv: kv[1]["rms_px"])
    print(
        f"narf-calibrate: {len(cameras)} cameras, mean reprojection {report['mean_reprojection_px']:.2f} px "
        f"(worst camera {worst[0]}: {worst[1]['rms_px']:.2f} px RMS); wrote {out}"
    )
    if "against_previous_annots" in report:
        diff = report["against_previous_annots"]["max"]
        print(
            f"narf-calibrate: against the capture's annots.npy: max centre difference {diff['centre_mm']:.1f} mm, "
            f"rotation {diff['rotation_deg']:.3f} deg, focal {diff['focal_pct']:.3f} % (after a similarity "
            f"alignment: {diff['aligned_centre_mm']:.1f} mm, {diff['aligned_rotation_deg']:.3f} deg)"
        )
    if args.write_annots:
        backup = merge_into_capture(args.capture, cameras)
        print(f"narf-calibrate: updated {args.capture / 'annots.npy'} (previous file: {backup.name})")
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-calibrate", main))
