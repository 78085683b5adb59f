"""Run benchmarks and print one Markdown table: ``python -m bench [synth ...]`` (default: all but ``levers``, the
fit's input corrections, which takes about two hours, ``poses``, the pose correction's harness, about half an
hour, and ``gap``, the training images against the held-out camera on the real recording and its synthetic analogue,
about an hour for its four default rows, and ``detail``, the part grids' time to quality against the preset before them,
about an hour and a half: these run only when named).

Each benchmark's rows are saved under ``$NARF_CACHE/rows/`` (``.cache/bench/rows/`` when unset) as it finishes, so that
an interrupted run loses only the benchmark it was in (the time-to-quality benchmark, the longest, also keeps each
finished configuration): ``--reuse`` takes the saved rows of benchmarks already measured on this machine and runs the
rest.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import json
import os
import sys
from pathlib import Path

from fitting.files import atomic_write_text
from pipelines.cli.common import flush_subnormals, keep_freed_memory, short_openmp_wait
from pipelines.datasets.smpl_files import cache_dir, chosen_cache

BENCHMARKS = {
    "synth": "bench.bench_synth",
    "models": "bench.bench_models",
    "calib": "bench.bench_calib",
    "autoencoder": "bench.bench_autoencoder",
    "quality": "bench.bench_quality",
    "views": "bench.bench_views",
    "viewer": "bench.bench_viewer",
    "levers": "bench.bench_levers",
    "poses": "bench.bench_poses",
    "gap": "bench.bench_gap",
    "consensus": "bench.bench_consensus",
    "detail": "bench.bench_detail",
}
#: Benchmarks that run only when named (hours of fitting: docs/results/real-capture.md).
ON_REQUEST = ("levers", "poses", "gap", "detail")


def _rows(name: str, saved: Path, reuse: bool, machine: str) -> list[dict]:
    """One benchmark's rows: the saved ones when ``reuse`` and they were measured on this machine, else measured now
    and saved."""
    if reuse and saved.exists():
        record = json.loads(saved.read_text())
        if record.get("machine") == machine:
            print(f"bench: {name}: reusing the rows saved in {saved} on {record['date']}", file=sys.stderr)
            return record["rows"]
    module = importlib.import_module(BENCHMARKS[name])
    # a benchmark that keeps each finished configuration (the time-to-quality one) takes --reuse for those too
    rows = module.run(reuse=reuse) if getattr(module, "KEEPS_CONFIGURATIONS", False) else module.run()
    record = {"machine": machine, "date": datetime.datetime.now().isoformat(timespec="minutes"), "rows": rows}
    atomic_write_text(saved, json.dumps(record, indent=1))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__)
    # no argparse ``choices``: with nargs="*" it checks the empty default against them (and would list it in --help)
    names = ", ".join(BENCHMARKS)
    parser.add_argument(
        "names",
        nargs="*",
        metavar="NAME",
        help=f"benchmarks to run, of {names} (default: all but {', '.join(ON_REQUEST)})",
    )
    parser.add_argument("--reuse", action="store_true", help="take the saved rows of benchmarks already run here")
    args = parser.parse_args()
    unknown = [name for name in args.names if name not in BENCHMARKS]
    if unknown:
        parser.error(f"unknown benchmark {unknown[0]!r} (choose from {names})")
    # as every command does before its first torch operation (docs/design.md, "OpenMP workers' wait", "Subnormal
    # numbers", "Memory allocator"); the spin count reaches the commands the benchmarks start through the environment
    short_openmp_wait()
    flush_subnormals()
    keep_freed_memory()
    # the benchmarks' own cache (runs, captures, rows) unless the user names one ($NARF_CACHE): chosen for this
    # process's calls, and passed to the commands the benchmarks start in their environment (command_environment)
    cache = os.environ.get("NARF_CACHE") or Path.cwd() / ".cache" / "bench"
    from bench.bench_models import machine

    rows = []
    with chosen_cache(cache):
        for name in args.names or [name for name in BENCHMARKS if name not in ON_REQUEST]:
            rows += _rows(name, cache_dir() / "rows" / f"{name}.json", args.reuse, machine())
    columns = list(dict.fromkeys(k for row in rows for k in row))
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))
    for row in rows:
        print("| " + " | ".join(str(row.get(c, "")) for c in columns) + " |")


if __name__ == "__main__":
    main()
