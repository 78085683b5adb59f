"""``narf-eval``: metrics of a fitted run on the protocol splits, both full-image and Neural Body crop."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.common import HelpFormatter, run_cli


def main(argv: list[str] | None = None) -> int:
    from fitting.evaluate import ALL_SPLITS, EVAL_SPLITS, markdown_table
    from fitting.trainer import auto_device
    from pipelines.evaluation import evaluate_run

    parser = argparse.ArgumentParser(
        prog="narf-eval",
        description="Render the held-out views of a split and report PSNR, SSIM (scikit-image, Gaussian 1.5) and "
        "Mask L2 (x10^4) per view and averaged, under the full-image and the Neural Body bounding-box crop "
        "protocols. Writes RUN/eval/metrics.json, RUN/eval/metrics.md (supplement layout) and image grids "
        "(ground truth | render | depth | part segmentation | error).",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--run", type=Path, required=True, help="run folder written by narf-fit --out")
    parser.add_argument(
        "--split",
        default="novel_pose",
        choices=ALL_SPLITS,
        help="novel_pose / novel_view are the Neural Body splits; 'all' = the four pose x view splits",
    )
    parser.add_argument("--limit", type=int, default=None, help="evaluate at most N views per split, evenly spread")
    parser.add_argument("--grids", type=int, default=4, help="image grids to write per split")
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    if not args.run.is_dir():
        raise FileNotFoundError(f"{args.run}: no such run folder")
    splits = list(EVAL_SPLITS) if args.split == "all" else [args.split]
    report = evaluate_run(args.run, splits, args.limit, str(auto_device(args.device)), not args.quiet, args.grids)
    print(markdown_table(report))
    print(f"narf-eval: wrote {args.run / 'eval' / 'metrics.json'}")
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-eval", main))
