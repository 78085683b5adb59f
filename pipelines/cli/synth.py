"""``narf-synth``: write synthetic data of the stand-in body in a real layout: a ZJU-MoCap multi-view capture
(default), a THUman-like set in NARF's ``render_128`` layout, or SURREAL-like clips."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from pipelines.cli.common import HelpFormatter, at_least, run_cli
from pipelines.synthetic.settings import (
    SYNTHETIC_SUBJECTS,
    Degradation,
    RigidSynthConfig,
    SurrealSynthConfig,
    SynthConfig,
    ThumanSynthConfig,
)


def build_parser() -> argparse.ArgumentParser:
    d = SynthConfig()
    parser = argparse.ArgumentParser(
        prog="narf-synth",
        description="Render synthetic data of the stand-in body in a real layout. --dataset zju (default): a "
        "multi-view capture (images, CIHP and binary masks, SMPL params and vertices, annots.npy, EasyMocap cameras, "
        "ChArUco calibration shots) that ZJU-MoCap loaders read unchanged; thuman: many people in NARF's render_128 "
        "layout (train / same_view / novel_view and the _view2 encoder inputs) plus raw THUman items; surreal: "
        "SURREAL clips (mp4, _info/_segm/_depth.mat) of unclothed people; rigid: a textured vehicle-like object under "
        "random rigid transforms and cameras (supplement Table B; 480 train / 20 test images at 200^2 in NARF's render "
        "layout). A finished set with the same settings is reused.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument(
        "--dataset", choices=("zju", "thuman", "surreal", "rigid"), default="zju", help="which layout to write"
    )
    parser.add_argument("--subject", default=d.subject, choices=SYNTHETIC_SUBJECTS, help="motion / subject name")
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default: <data-root>/synthetic/<subject>, or synthetic/thuman, synthetic/surreal, "
        "synthetic/rigid)",
    )
    parser.add_argument("--data-root", default=None, help="data root (default: $NARF_DATA or data/)")
    parser.add_argument(
        "--resolution",
        type=at_least(1, 8192),
        default=None,
        help="square image size in pixels (default: 512 for a subject, 200 for the rigid object; THUman and SURREAL "
        "keep their formats' fixed sizes)",
    )
    parser.add_argument(
        "--frames",
        type=at_least(1, 100_000),
        default=None,
        help="frames (30 fps) of the capture (zju: 300) or of each clip (surreal: 40)",
    )
    parser.add_argument("--cameras", type=at_least(1, 256), default=d.cameras, help="number of ring cameras")
    parser.add_argument("--seed", type=at_least(0), default=d.seed, help="seed of rig, motion and jitter")
    parser.add_argument(
        "--layout",
        choices=("standard", "313"),
        default=d.layout,
        help="image naming: Camera_B1/000000.jpg, or the CoreView_313/315 style (1-based)",
    )
    parser.add_argument(
        "--calib-shots",
        type=at_least(0, 1000),
        default=d.calib_shots,
        help="ChArUco board shots seen by the whole rig (0: no calib/ folder)",
    )
    parser.add_argument(
        "--calib-close-ups",
        type=at_least(0, 1000),
        default=d.calib_close_ups,
        help="per-camera close-up board shots under calib/<camera>/intrinsics/",
    )
    t, s = ThumanSynthConfig(), SurrealSynthConfig()
    parser.add_argument("--people", type=at_least(1, 10_000), default=t.people, help="thuman: number of people")
    parser.add_argument(
        "--train-poses", type=at_least(1, 10_000), default=t.train_poses, help="thuman: training meshes per person"
    )
    parser.add_argument(
        "--novel-poses", type=at_least(0, 10_000), default=t.novel_poses, help="thuman: held-out meshes per person"
    )
    parser.add_argument(
        "--renders-per-mesh", type=at_least(1, 1000), default=t.renders_per_mesh, help="thuman: train renders per mesh"
    )
    parser.add_argument(
        "--raw-items", type=at_least(0, 10_000), default=t.raw_items, help="thuman: meshes also written as raw items"
    )
    parser.add_argument(
        "--clips", type=at_least(1, 10_000), default=s.clips, help="surreal: number of clips (one person each)"
    )
    r = RigidSynthConfig()
    parser.add_argument("--train-images", type=at_least(1, 100_000), default=r.train, help="rigid: training images")
    parser.add_argument("--test-images", type=at_least(1, 100_000), default=r.test, help="rigid: test images")
    parser.add_argument("--workers", type=at_least(1, 256), default=d.workers, help="render processes")
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
    g = Degradation()
    parser.add_argument(
        "--degrade",
        type=Path,
        default=None,
        metavar="CAPTURE",
        help="instead of rendering, write a copy of the capture CAPTURE into --out with its inputs broken the way real "
        "recordings are (every joint turned, the body moved, each camera's colours scaled and offset) and the truth "
        "in degraded.json (docs/guides/synthetic-data.md)",
    )
    parser.add_argument(
        "--pose-noise", type=float, default=g.pose_degrees, help="--degrade: degrees each joint of each frame turns"
    )
    parser.add_argument(
        "--shift-noise", type=float, default=g.shift_m, help="--degrade: metres each frame's body moves"
    )
    parser.add_argument(
        "--colour-spread",
        type=float,
        default=g.colour_spread,
        help="--degrade: camera gains exp(u), u uniform in [-s, s], biases in [-s/4, s/4] (0: colours kept)",
    )
    return parser


def _degrade(args) -> int:
    if args.out is None:
        raise ValueError("--degrade writes a new capture: give --out")
    if not (args.degrade / "annots.npy").is_file():
        raise FileNotFoundError(f"{args.degrade}: no annots.npy (not a ZJU-MoCap capture)")
    from pipelines.synthetic.degrade import degrade_capture

    degradation = Degradation(args.pose_noise, args.shift_noise, args.colour_spread, args.seed)
    degradation.validate()
    out = degrade_capture(args.degrade, args.out, degradation)
    print(
        f"narf-synth: wrote {out} ({args.pose_noise:g} degrees per joint, {args.shift_noise:g} m, colour spread "
        f"{args.colour_spread:g}; the truth in {out / 'degraded.json'})"
    )
    return 0


def _other_dataset(args) -> int:
    from pipelines.datasets.subjects import data_root
    from pipelines.synthetic.rigid import generate_rigid, is_rigid_complete
    from pipelines.synthetic.surreal import generate_surreal, is_surreal_complete
    from pipelines.synthetic.thuman import generate_thuman, is_thuman_complete

    root = data_root(args.data_root)
    if args.dataset in ("thuman", "surreal") and args.resolution is not None:
        raise ValueError(f"--resolution: {args.dataset} images have their format's fixed size; leave it out")
    if args.dataset == "thuman":
        config = ThumanSynthConfig(
            args.people, args.train_poses, args.novel_poses, args.renders_per_mesh, args.raw_items, args.seed
        )
        out, complete, generate = args.out or root / "synthetic" / "thuman", is_thuman_complete, generate_thuman
    elif args.dataset == "rigid":
        resolution = args.resolution or RigidSynthConfig().resolution
        config = RigidSynthConfig(args.train_images, args.test_images, resolution, args.seed)
        out, complete, generate = args.out or root / "synthetic" / "rigid", is_rigid_complete, generate_rigid
    else:
        config = SurrealSynthConfig(clips=args.clips, frames=args.frames or SurrealSynthConfig().frames, seed=args.seed)
        out, complete, generate = args.out or root / "synthetic" / "surreal", is_surreal_complete, generate_surreal
    config.validate()
    if complete(out, config):
        print(f"narf-synth: {out} already holds this {args.dataset} set")
        return 0
    start = time.perf_counter()
    extra = {} if args.dataset == "rigid" else {"smpl_path": args.smpl_dir}
    generate(out, config, **extra)
    size = sum(p.stat().st_size for p in Path(out).rglob("*") if p.is_file()) / 1e6
    print(f"narf-synth: wrote the {args.dataset} set {out} ({size:.0f} MB) in {time.perf_counter() - start:.0f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.degrade is not None:
        return _degrade(args)
    if args.dataset != "zju":
        return _other_dataset(args)
    from pipelines.datasets.subjects import data_root, synthetic_path
    from pipelines.synthetic.capture import generate_capture, is_complete

    d = SynthConfig()
    config = SynthConfig(
        subject=args.subject,
        resolution=args.resolution or d.resolution,
        frames=args.frames or SynthConfig().frames,
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
