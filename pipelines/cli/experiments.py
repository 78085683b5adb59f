"""``narf-experiments``: the NARF supplement's Tables A, B and C as commands on the synthetic data (or real data
through --data-root), resumable, and their comparison with the supplement's numbers and orderings."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipelines.cli.common import HelpFormatter, at_least, positive_number, run_cli


def build_parser() -> argparse.ArgumentParser:
    from pipelines.experiments.runner import CPU_BUDGET, CPU_VIEWS

    parser = argparse.ArgumentParser(
        prog="narf-experiments",
        description="Run a table of the NARF supplement: fit every row with narf-fit for a time budget, evaluate it "
        "with narf-eval's protocol, and write OUT/<table>/table.md and table.json (cost columns: #params, FLOPs and "
        "activation memory per ray, steps and training rays/s; cells Mask L2 x10^4 / PSNR / SSIM per split) with the "
        "supplement's orderings checked. Rows are resumable: a finished row (OUT/<table>/<row>/result.json) is "
        "never recomputed, a killed one resumes from its checkpoint with the rest of its budget. 'compare' prints a "
        "finished table beside the supplement's numbers.",
        formatter_class=HelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser(
        "run",
        help="run (or resume) a table",
        formatter_class=HelpFormatter,
        description="table-a: autoencoders on the THUman-like set (CNN, P-NeRF, D-NARF, NARF_P, NARF_H, NARF_D); "
        "table-b: the rigid object (RP-NeRF, RT-NeRF w/o xi, RT-NeRF); table-c: the single subject (CNN, P-NeRF, "
        "D-NARF, NARF_P at widths 32-256, NARF_H, NARF_D, sigmoid, the tau sweep and the mask-loss ablations). "
        "With --preset cpu each row trains for "
        + ", ".join(f"{t}: {CPU_BUDGET[t]:g} min ({CPU_VIEWS[t] or 'all'} views per split)" for t in CPU_BUDGET)
        + ".",
    )
    run.add_argument("table", choices=("table-a", "table-b", "table-c"), help="which table of the supplement")
    run.add_argument("--out", type=Path, default=Path("runs/experiments"), help="output folder")
    run.add_argument(
        "--preset",
        choices=("cpu", "paper"),
        default="cpu",
        help="cpu: the CPU presets (cpu, ae_cpu, rigid_cpu) for a time budget per row; paper: the paper presets "
        "(meant for GPUs) for their full step counts unless --budget-minutes is given",
    )
    run.add_argument(
        "--budget-minutes", type=positive_number, default=None, help="training minutes per row (default: above)"
    )
    run.add_argument("--rows", default=None, help="comma-separated row names (default: all; see --list)")
    run.add_argument("--limit", type=at_least(1), default=None, help="views per split to evaluate (default: above)")
    run.add_argument("--data-root", default=None, help="data root or set folder passed to narf-fit")
    run.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    run.add_argument("--list", action="store_true", help="list the table's rows and exit")
    compare = sub.add_parser("compare", help="a finished table beside the supplement", formatter_class=HelpFormatter)
    compare.add_argument("results", type=Path, help="OUT/<table>/table.json or its folder")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from pipelines.experiments.compare import compare_markdown, load_summary

    if args.command == "compare":
        print(compare_markdown(load_summary(args.results)), end="")
        return 0
    from pipelines.experiments.runner import CPU_BUDGET, CPU_VIEWS, Settings, prepare_data, run_table
    from pipelines.experiments.tables import TABLES

    table = TABLES[args.table]
    if args.list:
        for row in table.rows:
            print(f"{row.name}\t{row.label}\t{' '.join(row.fit_args)}")
        return 0
    rows = None if args.rows is None else [r.strip() for r in args.rows.split(",") if r.strip()]
    unknown = sorted(set(rows or []) - {r.name for r in table.rows})
    if unknown:
        raise ValueError(
            f"{args.table} has no row {', '.join(unknown)} (rows: {', '.join(r.name for r in table.rows)})"
        )
    cpu = args.preset == "cpu"
    budget = args.budget_minutes if args.budget_minutes is not None else CPU_BUDGET[table.name] if cpu else None
    limit = args.limit if args.limit is not None else CPU_VIEWS[table.name] if cpu else None
    settings = Settings(args.preset, budget, limit, args.data_root, args.device)
    progress = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    prepare_data(table, settings)
    summary = run_table(table, args.out, settings, rows, progress=progress)
    print((args.out / table.name / "table.md").read_text(), end="")
    print(f"narf-experiments: wrote {args.out / table.name / 'table.json'} ({len(summary['rows'])} rows)")
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-experiments", main))
