"""``narf-prepare-thuman``: render raw THUman items into NARF's ``render_128`` autoencoder layout."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from pipelines.cli.common import HelpFormatter, run_cli


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="narf-prepare-thuman",
        description="Render raw THUman items (<item>/<frame>/ with mesh.obj, smpl_params.txt; listed by "
        "RAW_DIR/data_list.txt when present) into NARF's autoencoder layout: train/, same_view/, novel_view/ "
        "render_128 splits with their _view2 encoder inputs and bone_params, as NARF's render_THUman.py writes "
        "them (which needs Python 2 and opendr). narf-fit --kind autoencoder --data-root OUT trains on the result.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("raw_dir", type=Path, help="folder of raw THUman items")
    parser.add_argument("--out", type=Path, required=True, help="output folder (replaced when complete)")
    parser.add_argument("--renders-per-mesh", type=int, default=10, help="train renders per mesh (NARF: 10)")
    parser.add_argument(
        "--split-like",
        choices=("narf",),
        default="narf",
        help="narf: the first 90%% of the items train, the rest are novel poses (3545 of THUman's 3939)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the random rotations, scales and cameras")
    parser.add_argument("--smpl-dir", default=None, help="SMPL model file or folder (default: the stand-in)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from pipelines.synthetic.narf_render import prepare_thuman

    if not args.raw_dir.is_dir():
        raise FileNotFoundError(f"{args.raw_dir}: no such folder")
    if args.renders_per_mesh < 1:
        raise ValueError(f"--renders-per-mesh must be >= 1, got {args.renders_per_mesh}")
    if args.out.exists() and not args.out.is_dir():
        raise FileExistsError(f"{args.out}: exists and is a file")
    start = time.perf_counter()
    out = prepare_thuman(args.raw_dir, args.out, args.renders_per_mesh, 0.9, args.seed, args.smpl_dir)
    print(f"narf-prepare-thuman: wrote {out} in {time.perf_counter() - start:.0f} s")
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-prepare-thuman", main))
