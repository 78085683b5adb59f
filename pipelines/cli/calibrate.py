"""``narf-calibrate``: calibrate a multi-view rig from the ChArUco shots in ``CAPTURE_DIR/calib/<camera>/``."""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from collections import Counter
from dataclasses import asdict
from pathlib import Path

from fitting.files import merge_folder, partial_folder
from pipelines.calibration.board import BoardSpec, read_board_json
from pipelines.cli.common import HelpFormatter, at_least, positive_number, run_cli
from pipelines.datasets.colmap import write_colmap_model
from pipelines.datasets.easymocap import write_easymocap_cameras
from pipelines.datasets.rig_files import natural_key
from pipelines.datasets.zju_mocap import Camera, CaptureError, read_annots, write_annots


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


def _fixed_groups(text: str) -> frozenset[str]:
    from pipelines.calibration.rig import FIXABLE

    groups = frozenset(g.strip() for g in text.split(",") if g.strip() and g.strip() != "none")
    if groups - set(FIXABLE):
        raise ValueError(
            f"--fix {text}: unknown group(s) {sorted(groups - set(FIXABLE))}; choose from "
            f"{', '.join(sorted(FIXABLE))} or none"
        )
    return groups


def _camera_order(capture: Path, calib: Path) -> tuple[list[str], list[list[str]] | None, list[Camera] | None]:
    """The capture's camera order (annots.npy) when it has one, else the calib folders in natural order; also
    the capture's current cameras, when it has them."""
    annots = capture / "annots.npy"
    if annots.is_file():
        cameras, ims = read_annots(annots, image_size=(1, 1), check_folders=False)
        return [c.name for c in cameras], ims, cameras
    folders = sorted((p.name for p in calib.iterdir() if p.is_dir()), key=natural_key)
    return folders, None, None


def calibrate_capture(
    capture: Path, spec: BoardSpec, reference: str, progress: bool = True, fixed: frozenset[str] = frozenset({"k3"})
):
    """Detection, intrinsics, graph initialisation and bundle adjustment of every camera of a capture."""
    from tqdm import tqdm

    from pipelines.calibration.charuco import CalibrationError, calibrate_intrinsics, detect_folder
    from pipelines.calibration.rig import bundle_adjust, initial_extrinsics

    calib = capture / "calib"
    if not calib.is_dir():
        raise CaptureError(f"{calib}: no calib/ folder with ChArUco shots per camera")
    names, ims, previous = _camera_order(capture, calib)
    detections, intrinsics, reports, sizes = {}, {}, {}, {}
    for name in tqdm(names, desc="detecting boards", unit="camera", disable=not progress):
        if not (calib / name).is_dir():
            raise CalibrationError(f"{calib / name}: no calibration shots for camera {name}")
        found, size, report = detect_folder(calib / name, spec)
        if not found:
            reasons = ", ".join(f"{n} {r}" for r, n in Counter(report.values()).items())
            raise CalibrationError(
                f"camera {name} never sees the board ({len(report)} shots in {calib / name}: "
                f"{reasons}); check the board definition ({spec.squares_x}x{spec.squares_y} "
                f"squares of {spec.square_length} m, markers {spec.marker_length} m, "
                f"{spec.dictionary}) against the printed board"
            )
        detections[name], reports[name], sizes[name] = found, report, size
        intrinsics[name] = calibrate_intrinsics(name, found, size, fixed)
    cam_from_world, world_from_board = initial_extrinsics(intrinsics, detections, reference)
    solution = bundle_adjust(intrinsics, detections, reference, cam_from_world, world_from_board, fixed=fixed)
    cameras = [Camera(n, solution.K[n], solution.dist[n], solution.cam_from_world[n], *sizes[n]) for n in names]
    shared = {shot: pose for shot, pose in solution.world_from_board.items() if "/intrinsics/" not in shot}
    figures = {"world_from_board": shared, "camera_rms": solution.camera_rms}
    report = {
        "board": asdict(spec),
        "reference_shot": reference,
        "fixed": sorted(fixed),
        "mean_reprojection_px": solution.mean_error,
        "rms_px": solution.rms,
        "rejected_corners": solution.rejected,
        "cameras": {
            n: {
                "rms_px": solution.camera_rms[n],
                "shots_used": len(detections[n]),
                "intrinsics_only_rms_px": intrinsics[n].rms,
                "rejected_views": intrinsics[n].rejected,
                "detections": reports[n],
            }
            for n in names
        },
    }
    if previous is not None:
        from pipelines.calibration.report import compare_cameras

        report["against_previous_annots"] = compare_cameras(previous, cameras)
    return cameras, ims, report, figures


def write_outputs(out: Path, cameras: list[Camera], ims: list[list[str]] | None, report: dict, figures: dict) -> None:
    """Write into a hidden temporary folder, then move the files into ``out`` (nothing partial on failure)."""
    staging = partial_folder(out)
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    write_annots(staging / "annots.npy", cameras, ims or [])
    write_easymocap_cameras(staging, cameras)
    write_colmap_model(staging / "colmap", cameras)
    from pipelines.calibration.report import draw_residuals, draw_rig

    board = report["board"]
    size = (board["squares_x"] * board["square_length"], board["squares_y"] * board["square_length"])
    draw_rig(staging / "rig.png", cameras, figures["world_from_board"], size)
    draw_residuals(staging / "residuals.png", figures["camera_rms"])
    (staging / "report.json").write_text(json.dumps(report, indent=1))
    merge_folder(staging, out)


def merge_into_capture(capture: Path, cameras: list[Camera]) -> Path:
    """Replace the cams of ``capture/annots.npy`` (its ims kept), after backing the file up."""
    annots = capture / "annots.npy"
    if not annots.is_file():
        raise CaptureError(f"{annots}: --write-annots needs an existing annots.npy (its ims are kept)")
    _, ims = read_annots(annots, image_size=(1, 1), check_folders=False)
    backup = annots.with_name("annots.npy.bak")
    index = 1
    while backup.exists():
        backup, index = annots.with_name(f"annots.npy.bak{index}"), index + 1
    shutil.copy2(annots, backup)
    write_annots(annots, cameras, ims)
    return backup


def _corners(text: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) >= 2 for p in parts):
        raise argparse.ArgumentTypeError(f"expected inner corners as COLSxROWS with each >= 2 (e.g. 4x7), got '{text}'")
    return int(parts[0]), int(parts[1])


def checkerboard_intrinsics(args) -> int:
    """``--checkerboard``: per-camera intrinsics from checkerboard shots, written to intrinsics.json (and compared
    with ``--compare``)."""
    from fitting.files import atomic_write_bytes
    from pipelines.calibration.checkerboard import calibrate_checkerboard_shots, camera_name, shot_folders
    from pipelines.datasets.rig_files import read_rig

    square = args.square_length if args.square_length is not None else 0.06
    if not (square > 0 and square < 10):
        raise ValueError(f"--square-length {square}: expected a square side in metres, in (0, 10)")
    out = args.out or args.capture
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: exists and is not a folder")
    reference = {c.name: c for c in read_rig(args.compare)} if args.compare else {}  # read before the work
    names = [camera_name(f) for f in shot_folders(args.capture)]
    if reference and not set(names) & set(reference):
        raise ValueError(
            f"{args.compare}: none of its cameras {sorted(reference)} is one of the shots' cameras {names}; "
            "nothing to compare"
        )
    found = calibrate_checkerboard_shots(args.capture, args.checkerboard, square)
    report = {}
    for name, result in found.items():
        entry = {"K": result["K"].tolist(), "dist": result["dist"].tolist(), "size": list(result["size"])}
        entry |= {"rms_px": result["rms_px"], "shots_used": result["used"], "shots_rejected": result["rejected"]}
        K, k1 = result["K"], result["dist"][0]
        line = f"narf-calibrate: {name}: f = {K[0, 0]:.1f}, {K[1, 1]:.1f} px, k1 = {k1:+.4f}"
        line += f", RMS {result['rms_px']:.2f} px"
        line += f", {len(result['used'])} shots"
        if name in reference:
            focal = 100 * (result["K"][0, 0] / reference[name].K[0, 0] - 1)
            entry["focal_vs_reference_pct"] = focal
            line += f"; focal {focal:+.2f} % against {args.compare.name}"
        report[name] = entry
        print(line)
    atomic_write_bytes(out / "intrinsics.json", json.dumps(report, indent=1).encode())
    print(f"narf-calibrate: wrote {out / 'intrinsics.json'}")
    return 0


def main(argv: list[str] | None = None) -> int:
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
    args = parser.parse_args(argv)
    if not args.capture.is_dir():
        raise CaptureError(f"{args.capture}: no such capture folder")
    if args.checkerboard:
        return checkerboard_intrinsics(args)
    spec = _board(args, args.capture / "calib")
    fixed = _fixed_groups(args.fix)
    out = args.out or args.capture / "calibration"
    if out.exists() and not out.is_dir():  # checked before the calibration, not after
        raise FileExistsError(f"{out}: exists and is not a folder")
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
