"""Run benchmarks and print one Markdown table: ``python -m bench [synth ...]`` (default: all)."""

from __future__ import annotations

import argparse
import importlib
import os

from pipelines.cli.common import flush_subnormals, keep_freed_memory

BENCHMARKS = {
    "synth": "bench.bench_synth",
    "models": "bench.bench_models",
    "calib": "bench.bench_calib",
    "autoencoder": "bench.bench_autoencoder",
    "quality": "bench.bench_quality",
}


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__)
    parser.add_argument("names", nargs="*", choices=[*BENCHMARKS, []], help="benchmarks to run (default: all)")
    args = parser.parse_args()
    # as every command does before its first torch operation (docs/design.md, "Subnormal numbers", "Memory allocator")
    flush_subnormals()
    keep_freed_memory()
    os.environ.setdefault("NARF_CACHE", os.path.join(os.getcwd(), ".cache", "bench"))
    rows = []
    for name in args.names or list(BENCHMARKS):
        rows += importlib.import_module(BENCHMARKS[name]).run()
    columns = list(dict.fromkeys(k for row in rows for k in row))
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))
    for row in rows:
        print("| " + " | ".join(str(row.get(c, "")) for c in columns) + " |")


if __name__ == "__main__":
    main()
