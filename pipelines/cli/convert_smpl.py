"""``narf-convert-smpl``: convert an official (chumpy) SMPL pickle into a plain one smplx loads."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.common import run_cli
from pipelines.datasets.smpl_files import convert_official_pickle


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="narf-convert-smpl",
        description="Convert an official SMPL pickle (basicModel_*_lbs_10_207_0_v1.0.0.pkl, with chumpy objects) "
        "into a plain numpy/scipy pickle, without installing chumpy. Point --smpl-dir or NARF_SMPL_DIR at the "
        "output folder afterwards.",
    )
    parser.add_argument("src", type=Path, help="official SMPL .pkl")
    parser.add_argument("dst", type=Path, help="output, e.g. models/smpl/SMPL_NEUTRAL.pkl")
    args = parser.parse_args(argv)
    if args.dst.exists() and args.dst.is_dir():
        raise NotADirectoryError(f"{args.dst}: is a folder; give the output file name")
    convert_official_pickle(args.src, args.dst)
    print(f"narf-convert-smpl: wrote {args.dst}")
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-convert-smpl", main))
