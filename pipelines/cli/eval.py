"""``narf-eval``: metrics of a fitted run on the protocol splits, both full-image and Neural Body crop; for an
autoencoder run, the four THUman splits and the cross-dataset transfer to SURREAL beside the mean-code baseline."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.common import (
    HelpFormatter,
    add_samples,
    add_smpl_dir,
    at_least,
    own_context,
    positive_number,
    run_cli,
    samples_of,
    use_smpl_dir,
)

#: Every split name of every run kind (``pipelines.runs.kinds``; kept here so that ``--help`` loads no model code).
SPLITS = (
    "novel_pose",
    "novel_view",
    "same_pose_same_view",
    "same_pose_novel_view",
    "novel_pose_same_view",
    "novel_pose_novel_view",
    "cross_dataset",
    "test",
    "all",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="narf-eval",
        description="Render the held-out views of a split and report PSNR, SSIM (scikit-image, Gaussian 1.5) and "
        "Mask L2 (x10^4) per view and averaged, under the full-image and the Neural Body bounding-box crop "
        "protocols. Writes RUN/eval/metrics.json, RUN/eval/metrics.md (supplement layout) and image grids "
        "(ground truth | render | depth | part segmentation | error). An autoencoder run (narf-fit --kind "
        "autoencoder) is evaluated on same_pose_same_view, novel_pose_same_view, same_pose_novel_view, "
        "novel_pose_novel_view (the encoder sees a _view2 render of the same mesh) and cross_dataset (SURREAL: the "
        "code of a clip's first frame reconstructs it and renders the clip's later poses), next to the mean-code "
        "baseline; grids are encoder input | ground truth | render | depth | segmentation | error. A rigid-object run "
        "(narf-fit --kind rigid) is evaluated on its test images (--split test; supplement Table B).",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--run", type=Path, required=True, help="run folder written by narf-fit --out")
    parser.add_argument(
        "--split",
        default=None,
        action="append",
        choices=SPLITS,
        help="novel_pose / novel_view are the Neural Body splits; 'all' = the four pose x view splits (autoencoder: "
        "and cross_dataset; rigid object: test); repeat to evaluate several. Default: novel_pose for a subject "
        "run, novel_pose_novel_view for an autoencoder run, test for a rigid-object run",
    )
    parser.add_argument("--surreal", default=None, help="cross_dataset: SURREAL folder (default: the stand-in)")
    parser.add_argument(
        "--refine-steps",
        type=at_least(0),
        metavar="N",
        default=0,
        help="cross_dataset: also refine each encoded code on its input frame for N steps of the training loss "
        "(the field fixed; about 0.15 s per step for the CPU preset on 2 CPU cores) and report that code's "
        "row; its novel-pose cells are the fair measure, since the reconstruction is scored on the image it "
        "was refined on; 0 turns it off",
    )
    parser.add_argument(
        "--limit", type=at_least(1), default=None, help="evaluate at most N views per split, evenly spread"
    )
    parser.add_argument(
        "--frame-step",
        type=at_least(1),
        metavar="N",
        default=None,
        help="subject runs: evaluate every Nth frame of each split's frames, in place of the protocol's (every 30th; "
        "about five frames a range on a capture with fewer than 150 novel frames); 1: every frame",
    )
    parser.add_argument("--grids", type=at_least(0), default=4, help="image grids to write per split")
    parser.add_argument(
        "--mesh",
        action="store_true",
        help="also export the surface of each evaluated frame that has a true one (CAPTURE/surfaces/<frame>.ply, "
        "written by narf-synth) and report the symmetric surface distance (mean, 95th percentile, mm) and normal "
        "consistency; meshes in RUN/eval/meshes/<split>/",
    )
    parser.add_argument(
        "--mesh-resolution", type=at_least(8), default=256, help="--mesh: grid samples along the longest side"
    )
    parser.add_argument(
        "--mesh-level",
        type=positive_number,
        default=None,
        help="--mesh: density iso-level (default: as narf-export-mesh)",
    )
    parser.add_argument(
        "--capture",
        type=Path,
        default=None,
        metavar="OTHER",
        help="subject runs: evaluate on another prepared recording of the same person (same rig or another): every "
        "frame is a novel pose, every camera is evaluated, as the split 'capture'; instead of --split",
    )
    parser.add_argument(
        "--reference-params",
        type=Path,
        default=None,
        metavar="DIR",
        help="subject runs: a folder of ZJU-MoCap params of the capture's frames, named as the capture's own (the "
        "truth that narf-synth --degrade keeps, a marker-based fit, ...): report the mean joint error (cm) of the "
        "run's training poses and of the capture's own against it (RUN/eval/joints.json); alone, without --split, "
        "only this",
    )
    parser.add_argument(
        "--novel-colour",
        choices=("nearest", "own"),
        default=None,
        help="subject runs: the colour's pose features of frames the fit did not train on (novel poses, held-back "
        "frames, --capture): nearest, those of the trained frame whose pelvis stands nearest; own, their own (the "
        "paper). Default: the run's model.novel_colour (nearest unless the fit set it)",
    )
    add_samples(parser, "; recorded in metrics.json (docs/model.md §7)")
    add_smpl_dir(parser)
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


@own_context
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from fitting.files import folder_lock
    from fitting.run_folder import auto_device
    from pipelines.runs.kinds import open_run
    from pipelines.runs.requests import EvalRequest

    if not args.run.is_dir():
        raise FileNotFoundError(f"{args.run}: no such run folder")
    if args.capture is not None and args.split:
        raise ValueError("--capture evaluates the other recording as the split 'capture'; leave --split out")
    if args.capture is not None and not args.capture.is_dir():
        raise FileNotFoundError(f"{args.capture}: no such capture folder")
    if args.reference_params is not None and not args.reference_params.is_dir():
        raise FileNotFoundError(f"{args.reference_params}: no such params folder")
    samples = samples_of(args)
    use_smpl_dir(args.smpl_dir)
    kind, run = open_run(args.run)
    with folder_lock(args.run):  # not beside a fit (or another evaluation) of the same run; joints.json too
        if args.reference_params is not None:
            report_joints(kind, run, args.reference_params)
            if not args.split and args.capture is None:
                return 0
        request = EvalRequest(
            splits=("capture",) if args.capture is not None else kind.expand(args.run, args.split),
            limit=args.limit,
            device=str(auto_device(args.device)),
            progress=not args.quiet,
            grids=args.grids,
            mesh=args.mesh,
            mesh_resolution=args.mesh_resolution,
            mesh_level=args.mesh_level,
            surreal=args.surreal,
            refine_steps=args.refine_steps,
            capture=args.capture,
            novel_colour=args.novel_colour,
            samples=samples,
            frame_step=args.frame_step,
        )
        report = kind.evaluate(run, request)
    print(kind.markdown(report))
    print(f"narf-eval: wrote {args.run / 'eval' / 'metrics.json'}")
    return 0


def report_joints(kind, run, folder: Path) -> None:
    """``--reference-params``: the joint errors of a subject run's training poses, printed and written to
    RUN/eval/joints.json."""
    import json

    from fitting.files import atomic_write_text
    from pipelines.runs.subject.pose_check import reference_joint_errors
    from pipelines.runs.subject.session import load_run

    if kind.name != "subject":
        raise ValueError(f"--reference-params: {run.run_dir} is a {kind.name} run; joint errors are for subject runs")
    report = reference_joint_errors(load_run(run), folder)
    which = "corrected" if report["corrected"] else "the capture's (the fit did not correct them)"
    print(
        f"joint error against {folder} over {report['frames']} training frames: run's poses ({which}) "
        f"{report['run_joint_error_cm']:.2f} cm (p95 {report['run_joint_error_p95_cm']:.2f}), capture's own "
        f"{report['capture_joint_error_cm']:.2f} cm"
    )
    path = run.run_dir / "eval" / "joints.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(report, indent=1))
    print(f"narf-eval: wrote {path}")


def entrypoint() -> None:
    sys.exit(run_cli("narf-eval", main))


if __name__ == "__main__":  # python -m pipelines.cli.eval ...
    entrypoint()
