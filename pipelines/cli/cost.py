"""``narf-cost``: parameters, FLOPs and activation memory per ray of every model, with the supplement's values."""

from __future__ import annotations

import argparse
import sys

from pipelines.cli.common import run_cli

#: samples per ray of the cost accounting (narf.fields.base.SAMPLES_FOR_COST; docs/model.md §8), named here so that
#: the module loads without torch: the commands set torch's OpenMP wait before it loads (docs/design.md)
SAMPLES_FOR_COST = 96


def main(argv: list[str] | None = None) -> int:
    from narf.fields import build_model, model_spec, paper_presets, paper_rows

    presets = paper_presets()
    parser = argparse.ArgumentParser(
        prog="narf-cost",
        description="Print #params, FLOPs per ray and activation memory per ray of the paper-size models, counted "
        f"by upstream's rules ({SAMPLES_FOR_COST} samples per ray; the colour H->H/2 layer skipped), next to the "
        "NARF supplement's Tables A/C, plus the complete FLOP count. The image encoder is excluded.",
    )
    parser.add_argument("--model", choices=sorted(presets), help="only this model")
    args = parser.parse_args(argv)
    names = [args.model] if args.model else list(presets)
    print("| model | #params | FLOPs/ray | memory/ray | paper #params / FLOPs / memory | complete FLOPs/ray |")
    print("|---|---|---|---|---|---|")
    rows = {row.key: row for _, row in paper_rows()}
    for name in names:
        cost = presets[name].cost()
        ref = rows[name].cost
        paper = "-" if ref is None else f"{ref[0] / 1e6:.2f}M / {ref[1] / 1e6:.0f}M / {ref[2] / 1e3:.0f}K"
        print(
            f"| {rows[name].label} | {cost.params / 1e6:.2f}M | "
            f"{cost.flops_per_ray / 1e6:.0f}M | {cost.memory_per_ray / 1e3:.0f}K | {paper} | "
            f"{cost.flops_per_ray_complete / 1e6:.0f}M |"
        )
    if not args.model:
        cnn = model_spec("cnn").paper[0]
        params = sum(p.numel() for p in build_model("cnn").parameters()) / 1e6
        print(f"| {cnn.label} | {params:.2f}M | - | - | {cnn.cost[0] / 1e6:.1f}M / - / - | - |")
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-cost", main))
