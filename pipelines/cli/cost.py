"""``narf-cost``: parameters, FLOPs and activation memory per ray of every model, with the supplement's values."""

from __future__ import annotations

import argparse
import sys

from narf.fields import PAPER_COSTS, build_model, paper_presets
from narf.fields.base import SAMPLES_FOR_COST
from pipelines.cli.common import run_cli

_LABELS = {
    "p_nerf": "P-NeRF (pose in colour, eq. D)",
    "p_nerf_table": "P-NeRF (pose_in_color=false, as tables)",
    "narf_p": "NARF_P (256)",
    "narf_p_32": "NARF_P (32)",
    "narf_p_64": "NARF_P (64)",
    "narf_p_128": "NARF_P (128)",
    "narf_d": "NARF_D",
    "narf_d_sigmoid": "NARF_D sigmoid",
    "narf_h": "NARF_H",
    "d_narf": "D-NARF",
    "rt_nerf": "RT-NeRF",
    "rt_nerf_no_pose": "RT-NeRF w/o xi",
    "rp_nerf": "RP-NeRF",
}


def _fmt(value: float, unit: str) -> str:
    return f"{value / 1e6:.2f}M" if unit == "M" else f"{value / 1e3:.0f}K"


def main(argv: list[str] | None = None) -> int:
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
    for name in names:
        cost = presets[name].cost()
        ref = PAPER_COSTS.get(name)
        paper = "-" if ref is None else f"{ref[0] / 1e6:.2f}M / {ref[1] / 1e6:.0f}M / {ref[2] / 1e3:.0f}K"
        print(
            f"| {_LABELS[name]} | {cost.params / 1e6:.2f}M | "
            f"{cost.flops_per_ray / 1e6:.0f}M | {cost.memory_per_ray / 1e3:.0f}K | {paper} | "
            f"{cost.flops_per_ray_complete / 1e6:.0f}M |"
        )
    if not args.model:
        cnn = sum(p.numel() for p in build_model("cnn").parameters()) / 1e6
        print(f"| CNN baseline | {cnn:.2f}M | - | - | 15.6M / - / - | - |")
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-cost", main))
