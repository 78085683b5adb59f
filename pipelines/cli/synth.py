"""``narf-synth``: write a synthetic multi-view capture of the stand-in body in the ZJU-MoCap layout."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from pipelines.cli.common import HelpFormatter, run_cli
from pipelines.datasets.subjects import data_root, synthetic_path
from pipelines.synthetic.capture import SYNTHETIC_SUBJECTS, SynthConfig, generate_capture, is_complete


def build_parser() -> argparse.ArgumentParser:
    d = SynthConfig()
    parser = argparse.ArgumentParser(
        prog="narf-synth",
        description="Render a synthetic multi-view capture (images, CIHP and binary masks, SMPL params and "
        "vertices, annots.npy, EasyMocap cameras, ChArUco calibration shots) that ZJU-MoCap loaders read "
        "unchanged. A finished capture with the same settings is reused.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--subject", default=d.subject, choices=SYNTHETIC_SUBJECTS, help="motion / subject name")
    parser.add_argument(
        "--out", type=Path, default=None, help="output folder (default: <data-root>/synthetic/<subject>)"
    )
    parser.add_argument("--data-root", default=None, help="data root (default: $NARF_DATA or data/)")
    parser.add_argument("--resolution", type=int, default=d.resolution, help="square image size in pixels")
    parser.add_argument("--frames", type=int, default=d.frames, help="number of frames (30 fps)")
    parser.add_argument("--cameras", type=int, default=d.cameras, help="number of ring cameras")
    parser.add_argument("--seed", type=int, default=d.seed, help="seed of rig, motion and jitter")
    parser.add_argument(
        "--layout",
        choices=("standard", "313"),
        default=d.layout,
        help="image naming: Camera_B1/000000.jpg, or the CoreView_313/315 style (1-based)",
    )
    parser.add_argument(
        "--calib-shots",
        type=int,
        default=d.calib_shots,
        help="ChArUco board shots seen by the whole rig (0: no calib/ folder)",
    )
    parser.add_argument(
        "--calib-close-ups",
        type=int,
        default=d.calib_close_ups,
        help="per-camera close-up board shots under calib/<camera>/intrinsics/",
    )
    parser.add_argument("--workers", type=int, default=d.workers, help="render processes")
    parser.add_argument(
        "--lbs",
        action="store_true",
        help="also write animatable_nerf's lbs/ folder (blend-weight grids per frame: several MB a frame)",
    )
    parser.add_argument(
        "--smpl-dir",
        default=None,
        help="SMPL model file or folder (default: $NARF_SMPL_DIR, else the generated stand-in)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    config = SynthConfig(
        subject=args.subject,
        resolution=args.resolution,
        frames=args.frames,
        cameras=args.cameras,
        seed=args.seed,
        layout=args.layout,
        calib_shots=args.calib_shots,
        calib_close_ups=args.calib_close_ups,
        workers=args.workers,
        lbs=args.lbs,
    )
    out = args.out or synthetic_path(args.subject, data_root(args.data_root))
    if is_complete(out, config):
        print(f"narf-synth: {out} already holds this capture")
        return 0
    start = time.perf_counter()
    generate_capture(out, config, smpl_path=args.smpl_dir)
    size = sum(p.stat().st_size for p in Path(out).rglob("*") if p.is_file()) / 1e6
    print(
        f"narf-synth: wrote {out} ({config.frames} frames x {config.cameras} cameras at {config.resolution}^2, "
        f"{size:.0f} MB) in {time.perf_counter() - start:.0f} s"
    )
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-synth", main))
