"""``narf-prepare-capture``: a multi-camera recording (videos or image folders) and its calibration in, a
ZJU-MoCap-layout capture out, with a fitted body per frame, splits, overlays and a report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.common import HelpFormatter, at_least, attach_dash_values, positive_number, run_cli


def _frames(text: str) -> tuple[int, int | None]:
    """``A:B`` (B exclusive, either may be empty) -> (start, stop)."""
    start, sep, stop = text.partition(":")
    try:
        first = int(start) if start else 0
        last = int(stop) if stop else None
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A:B with whole numbers (e.g. 0:100), got '{text}'") from None
    if not sep or first < 0 or (last is not None and last <= first):
        raise argparse.ArgumentTypeError(f"expected A:B with 0 <= A < B (e.g. 0:100 or 20:), got '{text}'")
    return first, last


def _camera_map(text: str) -> dict[str, str]:
    pairs = [item.split("=", 1) for item in text.split(",") if item.strip()]
    if not pairs or any(len(p) != 2 or not p[0] or not p[1] for p in pairs):
        raise argparse.ArgumentTypeError(f"expected CAM=RECORDING[,CAM=RECORDING...], got '{text}'")
    return {k.strip(): v.strip() for k, v in pairs}


def _fraction(text: str) -> float:
    value = positive_number(text)
    if value >= 1:
        raise argparse.ArgumentTypeError(f"expected a fraction in (0, 1), got '{text}'")
    return value


def _floor(text: str):
    from pipelines.datasets.floor import parse_floor

    try:
        return parse_floor(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="narf-prepare-capture",
        description="Turn a synchronised multi-camera recording into a capture in the ZJU-MoCap layout that narf-fit "
        "--subject DIR, narf-eval and the Neural Body loaders read: frames, person masks, keypoints triangulated per "
        "joint, a body fitted to them per frame (params/, vertices/), splits.json (novel poses: the last frames; "
        "novel view: one held-out camera), overlay/ (the body drawn over every view, and overlay.mp4) and "
        "report.json (reprojection error and body-vs-mask IoU per camera, cameras that disagree, dropped frames). "
        "Keypoints and masks come from mediapipe (make venv-real) unless given.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument(
        "recording", type=Path, help="folder of per-camera videos (or videos/), or of per-camera image folders"
    )
    parser.add_argument(
        "--out", type=Path, required=True, help="capture folder to write (must not exist, see --overwrite)"
    )
    parser.add_argument(
        "--calibration",
        type=Path,
        default=None,
        help="Qualisys .qca.txt, Pose2Sim/Anipose .toml, EasyMocap folder (intri.yml + extri.yml), ZJU annots.npy, or "
        "a narf-calibrate output folder (default: the one found in RECORDING/calibration/ or RECORDING/)",
    )
    parser.add_argument(
        "--camera-map", type=_camera_map, default=None, help="CAM=RECORDING,... when names and order do not match"
    )
    parser.add_argument(
        "--frames", type=_frames, default=(0, None), help="frame range A:B of the recording (B exclusive; default all)"
    )
    parser.add_argument("--stride", type=at_least(1), default=1, help="keep every N-th frame")
    parser.add_argument(
        "--resolution",
        type=at_least(64),
        default=None,
        help="longest image side in pixels (default: as recorded; never enlarged)",
    )
    parser.add_argument(
        "--keypoints",
        type=Path,
        default=None,
        help="OpenPose-style JSON keypoints (BODY_25, BODY_25B, COCO-18, COCO-17, HALPE_26), one sub-folder per "
        "camera (default: mediapipe)",
    )
    parser.add_argument(
        "--keypoint-layout",
        choices=("body25", "body25b", "coco18", "coco17", "halpe26"),
        default=None,
        help="the layout of --keypoints (default: from the number of points; 25 points are told apart from their "
        "positions, and refused when they cannot be)",
    )
    parser.add_argument(
        "--smpl-params",
        type=Path,
        default=None,
        help="bodies you already have, instead of fitting them to the keypoints: EasyMocap's per-frame SMPL JSON "
        "(output/smpl/000000.json ...) or a ZJU-MoCap params/ folder; the silhouette stage may still polish them "
        "(--silhouette-iterations 0 keeps them as given)",
    )
    parser.add_argument(
        "--person",
        type=_person,
        default="best-seen",
        metavar="best-seen|largest|near:X,Y,Z|pixel:CAM:U,V|ID",
        help="whom to follow when several people are in view: best-seen (the default: most views agreeing on them "
        "over the recording), largest (in the images), near:X,Y,Z (nearest that point, metres in the calibration's "
        "world) or pixel:CAM:U,V (nearest that pixel of camera CAM when first seen); with --smpl-params, the "
        "person's id in those files (default: the only person)",
    )
    parser.add_argument(
        "--masks", type=Path, default=None, help="person mask images, one sub-folder per camera (default: mediapipe)"
    )
    parser.add_argument(
        "--sync",
        type=_sync,
        default="auto",
        metavar="auto|report|off|CAM=FRAMES,...",
        help="cameras in step: auto (the default) estimates each camera's time offset from the keypoints (the "
        "other cameras' triangulation reprojects best into it once each joint's static part, a calibration error's "
        "mark, is taken off, and the part that grows with the joint's place in the image where both agree), "
        "reports it with its confidence and, with one person in view, the masks' own estimate beside it (report.json "
        "'sync', the summary) and shifts by whole "
        "frames the cameras the capture's error asks to shift with high confidence (with several people in view it "
        "only reports); report estimates and reports only; off estimates nothing; CAM=FRAMES,... gives the offsets "
        "(a camera's frame t shows the others' t + FRAMES: a camera started 3 frames late is CAM=3)",
    )
    _choices(parser)
    return parser


def _sync(text: str):
    from pipelines.prepare.sync.apply import parse_sync

    try:
        return parse_sync(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err).removeprefix("--sync: ")) from None


def _choices(parser: argparse.ArgumentParser) -> None:
    """Options of the splits, the consensus, the body fit and the output."""
    parser.add_argument(
        "--holdout-camera",
        default=None,
        help="camera kept out of training for novel_view ('none': train on all; default: the last of 3 or more)",
    )
    parser.add_argument(
        "--novel-fraction", type=_fraction, default=0.3, help="last fraction of the frames kept for novel_pose"
    )
    parser.add_argument(
        "--max-error",
        type=positive_number,
        default=3.0,
        help="a view disagrees beyond this reprojection error, in %% of the image height",
    )
    parser.add_argument(
        "--fit-iterations",
        type=at_least(1),
        default=500,
        help="body-fit iterations (after 100 for the global placement)",
    )
    parser.add_argument(
        "--silhouette-iterations",
        type=at_least(0),
        default=400,
        help="last body-fit iterations in which the person masks take part beside the keypoints (robust chamfer "
        "distances between the projected body and each mask) and each camera's pose is corrected "
        "(docs/guides/real-captures.md); 0: keypoints only, the calibration as given",
    )
    parser.add_argument(
        "--fit-window",
        type=at_least(0),
        default=100,
        help="frames the body fit's last stage holds at once: a longer take is fitted in overlapping windows of "
        "this many frames, after the shape and the cameras are fitted on as many frames spread over the take, so "
        "that memory does not grow with the take's length (0: every frame at once)",
    )
    parser.add_argument(
        "--keep-flagged",
        action="store_true",
        help="write the capture even when every camera is flagged, for inspection (by default it is refused)",
    )
    parser.add_argument(
        "--keep-calibration",
        action="store_true",
        help="fit the body to the masks but leave the cameras exactly as the calibration gives them",
    )
    parser.add_argument(
        "--no-surface",
        action="store_true",
        help="fit the masks with the ten shape coefficients only: no displacement of each vertex along its normal "
        "(SMPL+D, written to body_surface.npy), as for a person in tight clothes or a body model that already "
        "fits",
    )
    parser.add_argument(
        "--smpl-dir",
        type=Path,
        default=None,
        help="SMPL model file or folder (default: $NARF_SMPL_DIR, else the stand-in)",
    )
    parser.add_argument(
        "--floor",
        type=_floor,
        default=None,
        metavar="auto|AXIS-up|AXIS-down[=COORD]",
        help="the floor, written to floor.json: 'auto' (default) finds it under the fitted feet; 'z-up', "
        "'y-down=0.02', ...: the world axis pointing up (or down) and the floor's coordinate on it, metres "
        "(a Qualisys world: 'z-up')",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace a capture this tool prepared before")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(attach_dash_values(argv, ("--frames",)))
    from pipelines.prepare.body.fit import FitSettings
    from pipelines.prepare.request import PrepareRequest
    from pipelines.prepare.run import prepare_capture

    if isinstance(args.person, int) and args.smpl_params is None:
        raise ValueError("--person ID picks a person of --smpl-params; give --smpl-params too")
    if args.keypoint_layout is not None and args.keypoints is None:
        raise ValueError("--keypoint-layout describes --keypoints files; give --keypoints too")
    request = PrepareRequest(
        recording=args.recording,
        out=args.out,
        calibration=args.calibration,
        start=args.frames[0],
        stop=args.frames[1],
        stride=args.stride,
        longest_side=args.resolution,
        keypoints=args.keypoints,
        keypoint_layout=args.keypoint_layout,
        keep_flagged=args.keep_flagged,
        smpl_params=args.smpl_params,
        person=args.person if isinstance(args.person, int) else None,
        follow=args.person if not isinstance(args.person, int) else "best-seen",
        masks=args.masks,
        camera_map=args.camera_map,
        holdout_camera=args.holdout_camera,
        novel_fraction=args.novel_fraction,
        threshold=args.max_error / 100,
        smpl_dir=args.smpl_dir,
        fit=FitSettings(
            iterations=args.fit_iterations,
            silhouette_iterations=args.silhouette_iterations,
            window=args.fit_window,
            refine_cameras=not args.keep_calibration,
            surface=not args.no_surface,
        ),
        floor=args.floor,
        overwrite=args.overwrite,
        progress=not args.quiet,
        sync=args.sync,
    )
    _print_summary(prepare_capture(request), args.out)
    return 0


def _print_summary(report: dict, out) -> None:
    """The report's summary: frames, reprojection, IoU, floor, notices, time offsets and one line per camera."""
    summary, frames = report["summary"], report["frames"]
    print(
        f"narf-prepare-capture: {frames['kept']} of {frames['common']} frames kept, {len(report['cameras'])} cameras; "
        f"median reprojection {summary['median_reprojection_pct_height']:.2f} % of the image height, lowest camera "
        f"IoU {summary['min_camera_iou']:.2f}; wrote {out}"
    )
    floor = report["floor"]
    print(
        f"  floor ({floor['source']}): height {floor['height']:.3f} m along up {[round(v, 3) for v in floor['up']]}; "
        f"the body's lowest point {floor['lowest_point_cm_median']:.1f} cm above it (median frame)"
    )
    surface = summary.get("surface_displacement_cm")
    if surface:
        print(f"  the body's surface displaced a median {surface['median']:.1f} cm (99 %: {surface['p99']:.1f} cm)")
    for notice in report["notices"]:
        print(f"  note: {notice}")
    if "person" in report:
        p = report["person"]
        others = p["people_seen"] - 1
        seen_too = f"; {others} other(s) seen, left out" if others else ""
        again = f"; {p['views_detected_again']} views detected again around them" if p["views_detected_again"] else ""
        unseen = p.get("people_without_mask", 0)
        dropped = f"; {unseen} in the keypoint files but in no view's mask, dropped" if unseen else ""
        print(f"  following {p['followed']}{seen_too}{again}{dropped}")
    if "detections" in report:
        d = report["detections"]
        size = f": {d['cache_files']} files, {d['cache_mb']} MB" if "cache_files" in d else ""
        print(f"  detections: {d['reused']} views reused, {d['detected']} detected (kept in {d['cache']}{size})")
    _print_sync(report["sync"])
    _print_colour(report.get("colour"))
    for name, camera in report["cameras"].items():
        error, share = camera["body_reprojection_px"], camera["body_reprojection_pct_height"]
        flag = f"  FLAGGED: {camera['flag']}" if "flag" in camera else ""
        moved = _correction_text(camera.get("calibration_correction"))
        source = f" ({camera['recording']}, matched by {camera['matched_by']})" if "recording" in camera else ""
        print(
            f"  {name}{source}: reprojection {error:.1f} px ({share:.2f} %), IoU {camera['iou_mean']:.2f}, views used "
            f"{camera['views_used']}{moved}{flag}"
        )


def _correction_text(moved: dict | None) -> str:
    """The summary's words for a camera's ``calibration_correction`` (docs/guides/real-captures.md, step 6)."""
    if not moved:
        return ""
    text = f", calibration corrected by {moved['turn_degrees']:.2f} deg / {moved['shift_cm']:.1f} cm"
    depth = moved.get("depth_cm", 0.0)
    if depth:
        text += f", then moved {abs(depth):.1f} cm {'nearer the person' if depth > 0 else 'further away'}"
    if "depth_skipped" in moved:
        text += f", distance not checked ({moved['depth_skipped']})"
    return text


def _person(text: str):
    """``--person``: a person's id (an integer, for --smpl-params) or whom to follow (``prepare.people.tracks``)."""
    from pipelines.prepare.people.tracks import parse_person

    if text.lstrip("-").isdigit():
        return int(text)
    try:
        return parse_person(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _print_colour(colour: dict | None) -> None:
    """One line of the cameras' colour gains (report.json 'colour', colour.json)."""
    if colour:
        from pipelines.prepare.layout.colour import colour_summary

        print(f"  camera colour, {colour_summary(colour)}")


def _print_sync(sync: dict) -> None:
    """One line of the cameras' time offsets (report.json 'sync')."""
    if sync.get("mode") == "off":
        print("  cameras taken as in step (--sync off)")
        return
    parts = []
    for name, entry in sync.get("cameras", {}).items():
        if "status" not in entry:
            parts.append(f"{name} not estimated")
            continue
        shifted = f", shifted {entry['applied_frames']:+d}" if entry["applied_frames"] else ""
        looks = [(what, entry.get(what, {})) for what in ("keypoints", "silhouettes")]
        look = "".join(f"; {what} {it['offset_frames']:+.1f}" for what, it in looks if "offset_frames" in it)
        parts.append(f"{name} {entry['offset_frames']:+.1f} {entry['status']} ({entry['confidence']}{shifted}{look})")
    note = f"; {sync['note']}" if sync.get("note") else ""
    print(f"  time offsets in frames ({sync.get('mode')}{note}): " + ", ".join(parts))


def entrypoint() -> None:
    sys.exit(run_cli("narf-prepare-capture", main))
