"""The calibration workflows behind ``narf-calibrate``: a ChArUco rig (detection, per-camera intrinsics, a graph over
the shots that several cameras see, one joint bundle adjustment; docs/guides/calibration.md) and checkerboard
intrinsics; where their outputs go (staged, then moved into place: ``fitting.files``)."""

from __future__ import annotations

import json
import shutil
from collections import Counter
from dataclasses import asdict
from pathlib import Path

from tqdm import tqdm

from fitting.files import atomic_write_bytes, fresh_partial, merge_folder, writes_folder
from pipelines.calibration.board import BoardSpec
from pipelines.calibration.charuco import CalibrationError, calibrate_intrinsics, detect_folder
from pipelines.calibration.report import compare_cameras, draw_residuals, draw_rig
from pipelines.calibration.rig import FIXABLE, bundle_adjust, initial_extrinsics
from pipelines.datasets.camera import Camera
from pipelines.datasets.colmap import write_colmap_model
from pipelines.datasets.easymocap import write_easymocap_cameras
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.rig_files import natural_key, read_rig
from pipelines.datasets.zju_mocap import read_annots, write_annots


def fixed_groups(text: str) -> frozenset[str]:
    """``--fix``: the comma-separated parameter groups held fixed (``rig.FIXABLE``; ``none``: all free)."""
    groups = frozenset(g.strip() for g in text.split(",") if g.strip() and g.strip() != "none")
    if groups - set(FIXABLE):
        raise ValueError(
            f"--fix {text}: unknown group(s) {sorted(groups - set(FIXABLE))}; choose from "
            f"{', '.join(sorted(FIXABLE))} or none"
        )
    return groups


def camera_order(capture: Path, calib: Path) -> tuple[list[str], list[list[str]] | None, list[Camera] | None]:
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
    calib = capture / "calib"
    if not calib.is_dir():
        raise CaptureError(f"{calib}: no calib/ folder with ChArUco shots per camera")
    names, ims, previous = camera_order(capture, calib)
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
        report["against_previous_annots"] = compare_cameras(previous, cameras)
    return cameras, ims, report, figures


@writes_folder()
def write_outputs(out: Path, cameras: list[Camera], ims: list[list[str]] | None, report: dict, figures: dict) -> None:
    """Write into a hidden temporary folder, then move the files into ``out`` (nothing partial on failure; one
    writer at a time)."""
    staging = fresh_partial(out)
    write_annots(staging / "annots.npy", cameras, ims or [])
    write_easymocap_cameras(staging, cameras)
    write_colmap_model(staging / "colmap", cameras)
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


def checkerboard_intrinsics(
    shots: Path, corners: tuple[int, int], square: float | None, compare: Path | None, out: Path
) -> list[str]:
    """Per-camera intrinsics from checkerboard shots (one folder per camera, Pose2Sim's ``int_<camera>_img``) with
    ``corners`` inner corners and squares of ``square`` metres (None: 0.06), compared with the cameras of the
    calibration file ``compare``; writes ``out/intrinsics.json`` and returns one summary line per camera. The flags
    are checked before any shot is read."""
    from pipelines.calibration.checkerboard import calibrate_checkerboard_shots, camera_name, shot_folders

    square = square if square is not None else 0.06
    if not (square > 0 and square < 10):
        raise ValueError(f"--square-length {square}: expected a square side in metres, in (0, 10)")
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: exists and is not a folder")
    reference = {c.name: c for c in read_rig(compare)} if compare else {}  # read before the work
    names = [camera_name(f) for f in shot_folders(shots)]
    if reference and not set(names) & set(reference):
        raise ValueError(
            f"{compare}: none of its cameras {sorted(reference)} is one of the shots' cameras {names}; "
            "nothing to compare"
        )
    found = calibrate_checkerboard_shots(shots, corners, square)
    report, lines = {}, []
    for name, result in found.items():
        entry = {"K": result["K"].tolist(), "dist": result["dist"].tolist(), "size": list(result["size"])}
        entry |= {"rms_px": result["rms_px"], "shots_used": result["used"], "shots_rejected": result["rejected"]}
        K, k1 = result["K"], result["dist"][0]
        line = f"{name}: f = {K[0, 0]:.1f}, {K[1, 1]:.1f} px, k1 = {k1:+.4f}"
        line += f", RMS {result['rms_px']:.2f} px"
        line += f", {len(result['used'])} shots"
        if name in reference:
            focal = 100 * (result["K"][0, 0] / reference[name].K[0, 0] - 1)
            entry["focal_vs_reference_pct"] = focal
            line += f"; focal {focal:+.2f} % against {compare.name}"
        report[name] = entry
        lines.append(line)
    atomic_write_bytes(out / "intrinsics.json", json.dumps(report, indent=1).encode())
    return [*lines, f"wrote {out / 'intrinsics.json'}"]
