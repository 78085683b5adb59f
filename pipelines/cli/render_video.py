"""``narf-render-video``: mp4 videos of a fitted avatar (orbit, pose sequences, bone-length edits), or of people
encoded by an autoencoder run (orbit, poses, interpolation between two people)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.common import (
    HelpFormatter,
    add_motion_fps,
    add_samples,
    add_smpl_dir,
    at_least,
    own_context,
    positive_number,
    run_cli,
    samples_of,
    use_smpl_dir,
)

#: The video kinds of subject and autoencoder runs (``pipelines.runs.kinds``; here so ``--help`` loads no model code).
VIDEO_KINDS = ("bones", "interpolate", "orbit", "path", "poses")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="narf-render-video",
        description="Render an H.264 mp4 from a fitted run, side by side RGB | depth | part segmentation: 'orbit' "
        "circles a held pose at the rig's distance and height; 'poses' plays the held-out frames (or another "
        "motion capture given with --motion) from one camera; 'bones' grows and shrinks "
        "the legs (bone-length edit); 'path' (or --camera-path FILE) flies along the keyframes saved by narf-view. "
        "For an autoencoder run (narf-fit --kind autoencoder), --input encodes a person "
        "(a render_128 color_XXXXXXXX.png with its pose files beside it, or a SURREAL <clip>_info.mat[:FRAME]) and "
        "'orbit' circles that person, 'poses' plays the set's held-out poses on the person's skeleton, "
        "'interpolate' (two --input) morphs z_s and z_a from the first person to the second; frames are "
        "input | RGB | depth | segmentation.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--run", type=Path, required=True, help="run folder written by narf-fit --out")
    parser.add_argument("--kind", choices=VIDEO_KINDS, default=None, help="what to render (default: orbit)")
    parser.add_argument(
        "--input",
        dest="inputs",
        action="append",
        default=[],
        help="autoencoder runs: the person to encode (repeat for --kind interpolate)",
    )
    parser.add_argument(
        "--refine-steps",
        type=at_least(0),
        metavar="N",
        default=0,
        help="autoencoder runs: refine each input's code for N steps of the training loss on that input before "
        "rendering (the field fixed; about 0.15 s per step for the CPU preset on 2 CPU cores; docs/model.md "
        "section 4); 0 renders the encoder's code as it is",
    )
    parser.add_argument(
        "--camera-path",
        type=Path,
        default=None,
        help="a camera path saved by narf-view ('save camera path'): --frames cameras interpolated along its "
        "keyframes, at its image size, each showing its keyframes' capture frame (implies --kind path)",
    )
    parser.add_argument("--out", type=Path, default=None, help="output .mp4 (default: RUN/videos/<kind>.mp4)")
    parser.add_argument("--frames", type=at_least(1), default=60, help="number of video frames (at most)")
    parser.add_argument(
        "--fps",
        type=at_least(1),
        default=24,
        help="frames per second; a --motion is resampled to it (slerp) from its own rate",
    )
    parser.add_argument(
        "--camera", type=at_least(0), default=None, help="camera index for poses/bones (default: first test view)"
    )
    parser.add_argument(
        "--motion",
        "--params-dir",
        dest="motion",
        type=Path,
        default=None,
        help="poses: a motion to play with this subject's shape: an AMASS .npz (SMPL+H or SMPL-X), a ZJU-MoCap "
        "params/ or new_params/ folder, or a SURREAL <clip>_info.mat; it is stood on the capture's floor at the "
        "centre of the training poses, facing where they face; RUN/videos/<name>.json lists the frames whose parts "
        "leave the trained range",
    )
    parser.add_argument("--start", type=at_least(0), default=0, help="--motion: first source frame")
    add_motion_fps(parser)
    parser.add_argument("--scale", type=positive_number, default=1.3, help="bones: largest leg-length factor")
    add_smpl_dir(parser)
    add_samples(parser, ", as narf-eval --samples")
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


@own_context
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from fitting.files import folder_lock
    from fitting.run_folder import auto_device
    from pipelines.runs.kinds import open_run
    from pipelines.runs.requests import VideoRequest, a_run

    use_smpl_dir(args.smpl_dir)
    if args.camera_path is not None and args.kind not in (None, "path"):
        raise ValueError(f"--camera-path renders the path's cameras; it cannot be a --kind {args.kind} video too")
    if args.camera_path is not None:
        args.kind = "path"
    elif args.kind is None:
        args.kind = "orbit"
    elif args.kind == "path":
        raise ValueError("--kind path renders a camera path: give --camera-path FILE (saved by narf-view)")
    samples = samples_of(args)
    out = args.out or args.run / "videos" / f"{args.kind}.mp4"
    if not args.run.is_dir():
        raise FileNotFoundError(f"{args.run}: no such run folder")
    if out.is_dir():  # checked before rendering, not after
        raise IsADirectoryError(f"{out}: is a folder; give a .mp4 file name")
    if out.suffix.lower() != ".mp4":  # the writer makes H.264 in an MP4 container, whatever the name says
        raise ValueError(f"{out}: the video is an H.264 MP4; give a .mp4 file name")
    kind, run = open_run(args.run)
    if kind.render is None or args.kind not in kind.videos:
        offered = f"--kind {', '.join(kind.videos)}" if kind.videos else "no videos"
        raise ValueError(f"{args.run}: {a_run(kind.name)}; it renders {offered}, not '{args.kind}'")
    request = VideoRequest(
        kind=args.kind,
        out=out,
        frames=args.frames,
        fps=args.fps,
        device=str(auto_device(args.device)),
        progress=not args.quiet,
        inputs=tuple(args.inputs),
        refine_steps=args.refine_steps,
        motion=args.motion,
        camera=args.camera,
        scale=args.scale,
        start=args.start,
        motion_fps=args.motion_fps,
        camera_path=args.camera_path,
        samples=samples,
    )
    with folder_lock(out):  # one writer per video file
        written = kind.render(run, request)
    print(f"narf-render-video: wrote {written}")
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-render-video", main))
