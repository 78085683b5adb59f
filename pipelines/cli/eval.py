"""``narf-eval``: metrics of a fitted run on the protocol splits, both full-image and Neural Body crop; for an
autoencoder run, the four THUman splits and the cross-dataset transfer to SURREAL beside the mean-code baseline."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.common import HelpFormatter, run_cli


def build_parser() -> argparse.ArgumentParser:
    from fitting.evaluate import ALL_SPLITS
    from pipelines.autoencoder_evaluation import AUTOENCODER_SPLITS

    parser = argparse.ArgumentParser(
        prog="narf-eval",
        description="Render the held-out views of a split and report PSNR, SSIM (scikit-image, Gaussian 1.5) and "
        "Mask L2 (x10^4) per view and averaged, under the full-image and the Neural Body bounding-box crop "
        "protocols. Writes RUN/eval/metrics.json, RUN/eval/metrics.md (supplement layout) and image grids "
        "(ground truth | render | depth | part segmentation | error). An autoencoder run (narf-fit --dataset "
        "thuman) is evaluated on same_pose_same_view, novel_pose_same_view, same_pose_novel_view, "
        "novel_pose_novel_view (the encoder sees a _view2 render of the same mesh) and cross_dataset (SURREAL: the "
        "code of a clip's first frame reconstructs it and renders the clip's later poses), next to the mean-code "
        "baseline; grids are encoder input | ground truth | render | depth | segmentation | error. A rigid-object run "
        "(narf-fit --dataset rigid) is evaluated on its test images (--split test; supplement Table B).",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--run", type=Path, required=True, help="run folder written by narf-fit --out")
    parser.add_argument(
        "--split",
        default=None,
        action="append",
        choices=sorted(set(ALL_SPLITS) | set(AUTOENCODER_SPLITS) | {"test"}),
        help="novel_pose / novel_view are the Neural Body splits; 'all' = the four pose x view splits (autoencoder: "
        "and cross_dataset; rigid object: test); repeat to evaluate several. Default: novel_pose, test for a "
        "rigid-object run",
    )
    parser.add_argument("--surreal", default=None, help="cross_dataset: SURREAL folder (default: the stand-in)")
    parser.add_argument(
        "--refine-steps",
        type=int,
        metavar="N",
        default=0,
        help="cross_dataset: also refine each encoded code on its input frame for N steps of the training loss "
        "(the field fixed; about 0.15 s per step for the CPU preset on 2 CPU cores) and report that code's "
        "row; its novel-pose cells are the fair measure, since the reconstruction is scored on the image it "
        "was refined on; 0 turns it off",
    )
    parser.add_argument("--limit", type=int, default=None, help="evaluate at most N views per split, evenly spread")
    parser.add_argument("--grids", type=int, default=4, help="image grids to write per split")
    parser.add_argument(
        "--mesh",
        action="store_true",
        help="also export the surface of each evaluated frame that has a true one (CAPTURE/surfaces/<frame>.ply, "
        "written by narf-synth) and report the symmetric surface distance (mean, 95th percentile, mm) and normal "
        "consistency; meshes in RUN/eval/meshes/<split>/",
    )
    parser.add_argument("--mesh-resolution", type=int, default=256, help="--mesh: grid samples along the longest side")
    parser.add_argument(
        "--mesh-level", type=float, default=None, help="--mesh: density iso-level (default: as narf-export-mesh)"
    )
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def main(argv: list[str] | None = None) -> int:
    from fitting.checkpoint import load_checkpoint
    from fitting.trainer import auto_device

    args = build_parser().parse_args(argv)
    if args.refine_steps < 0:
        raise ValueError(f"--refine-steps must be >= 0, got {args.refine_steps}")
    if not args.run.is_dir():
        raise FileNotFoundError(f"{args.run}: no such run folder")
    device = str(auto_device(args.device))
    state = load_checkpoint(args.run)
    if args.refine_steps and state.get("kind") != "autoencoder":
        raise ValueError(f"{args.run}: --refine-steps is for autoencoder runs (narf-fit --dataset thuman)")
    if state["config"].get("data", {}).get("dataset") == "rigid":
        table = _evaluate_rigid(args, device)
    elif state.get("kind") == "autoencoder":
        table = _evaluate_autoencoder(args, device)
    else:
        table = _evaluate_subject(args, device)
    print(table)
    print(f"narf-eval: wrote {args.run / 'eval' / 'metrics.json'}")
    return 0


def _evaluate_rigid(args: argparse.Namespace, device: str) -> str:
    """A rigid-object run: its one split, ``test``; returns the markdown table."""
    from pipelines.rigid_session import evaluate_rigid_run, markdown_rigid

    if args.mesh or not set(args.split or []) <= {"test", "all"}:
        raise ValueError(f"{args.run}: a rigid-object run; it has one split, test (and no --mesh)")
    return markdown_rigid(evaluate_rigid_run(args.run, args.limit, device, not args.quiet, args.grids))


def _evaluate_autoencoder(args: argparse.Namespace, device: str) -> str:
    """An autoencoder run: the THUman splits and cross_dataset beside the mean code; returns the markdown table."""
    from pipelines.autoencoder_evaluation import AUTOENCODER_SPLITS, evaluate_autoencoder_run, markdown_autoencoder

    requested = args.split or ["novel_pose"]
    if args.mesh:
        raise ValueError(f"{args.run}: --mesh is for per-subject fits (an autoencoder run has no true surfaces)")
    if not set(requested) <= {*AUTOENCODER_SPLITS, "all"}:
        raise ValueError(f"{args.run}: an autoencoder run; choose --split from {', '.join(AUTOENCODER_SPLITS)}, all")
    splits = _expand(requested, AUTOENCODER_SPLITS)
    if args.refine_steps and "cross_dataset" not in splits:
        raise ValueError(f"{args.run}: --refine-steps refines SURREAL codes; it needs --split cross_dataset or all")
    report = evaluate_autoencoder_run(
        args.run, splits, args.limit, device, not args.quiet, args.grids, args.surreal, args.refine_steps
    )
    return markdown_autoencoder(report)


def _evaluate_subject(args: argparse.Namespace, device: str) -> str:
    """A per-subject fit: the protocol splits (and, with ``--mesh``, surface distances); returns the markdown table."""
    from fitting.evaluate import ALL_SPLITS, EVAL_SPLITS, markdown_table
    from pipelines.autoencoder_evaluation import AUTOENCODER_SPLITS
    from pipelines.evaluation import evaluate_run

    requested = args.split or ["novel_pose"]
    for split in requested:
        if split not in ALL_SPLITS:
            kind = "an autoencoder split" if split in AUTOENCODER_SPLITS else "the rigid-object split"
            raise ValueError(f"{args.run}: a per-subject fit; '{split}' is {kind}")
    splits = _expand(requested, EVAL_SPLITS)
    report = evaluate_run(
        args.run,
        splits,
        args.limit,
        device,
        not args.quiet,
        args.grids,
        args.mesh,
        args.mesh_resolution,
        args.mesh_level,
    )
    return markdown_table(report)


def _expand(requested: list[str], every: tuple[str, ...]) -> list[str]:
    """The splits to evaluate: ``all`` stands for ``every``; each split once, in the order first named."""
    return list(dict.fromkeys(name for split in requested for name in (every if split == "all" else (split,))))


def entrypoint() -> None:
    sys.exit(run_cli("narf-eval", main))
