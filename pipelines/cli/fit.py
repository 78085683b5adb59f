"""``narf-fit``: fit an avatar to one subject (synthetic stand-in when no real capture is found), train the
autoencoder across people on a THUman-layout set (``--kind autoencoder``), or fit a rigid object (``--kind rigid``).
The work is ``pipelines.runs.fit.fit``; this module turns flags into its request."""

from __future__ import annotations

import argparse
import sys
import typing
from pathlib import Path

from fitting.config import LEGACY_KINDS, RunKindName
from pipelines.cli.common import HelpFormatter, positive_number, run_cli

#: The run kinds (``--kind``), and the names older versions took for them (``--dataset``, a hidden alias).
KIND_NAMES = typing.get_args(RunKindName)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="narf-fit",
        description="Fit a NARF avatar (default NARF_D) to a multi-view capture in the ZJU-MoCap layout, or with "
        "--kind autoencoder train the NARF autoencoder (image encoder + latent-conditioned field) across the people "
        "of a THUman render_128 set (--data-root: the set's folder; default: the synthetic stand-in), or with --kind "
        "rigid fit a rigid-object model (RT-NeRF, RT-NeRF w/o xi, RP-NeRF; supplement Table B). Writes "
        "config.yaml, checkpoint.pt (atomic, every few minutes and at the end), log.jsonl, curve.png and val/ "
        "renders into --out. A killed fit resumes with --resume and ends where an uninterrupted one would.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument(
        "--kind",
        choices=KIND_NAMES,
        default=None,
        help="subject: one avatar per capture (default); autoencoder: across the people of a THUman-layout set "
        "(presets ae_cpu / ae_paper; --model p_nerf and narf_h train at lr 0.001 there, as in the supplement); "
        "rigid: one rigid object (presets rigid_cpu / rigid_paper; --data-root: the set, default the synthetic "
        "stand-in)",
    )
    parser.add_argument("--dataset", choices=tuple(LEGACY_KINDS), default=None, help=argparse.SUPPRESS)
    parser.add_argument("--subject", default=None, help="subject name or folder (default from the preset: taichi)")
    parser.add_argument("--data-root", default=None, help="data root (default: $NARF_DATA or data/)")
    parser.add_argument(
        "--config",
        default=None,
        help="preset name (cpu, cpu_grid, gpu_grid, paper, paper_sparse, tiny, cnn, ae_cpu, ae_paper, ae_tiny, ae_cnn, "
        "ae_cnn_paper, rigid_cpu, rigid_paper, rigid_tiny) or YAML file; default: cnn for --model cnn, ae_paper / "
        "ae_cpu for --kind autoencoder (ae_cnn_paper / ae_cnn with --model cnn), rigid_paper / rigid_cpu for --kind "
        "rigid, else paper with CUDA and cpu without (cpu_grid: the cpu preset whose NARF_D parts read learned grids, "
        "on a random background, with Adam's beta2 0.99 and 32 images of 16 rays a step; gpu_grid: the grids at GPU "
        "scale; paper_sparse: the paper's network with the cpu preset's colour and shells, for rigs of few cameras)",
    )
    parser.add_argument(
        "--model",
        default=None,
        help="model name (narf_d, narf_d_sigmoid, narf_h, narf_p, p_nerf, d_narf, or cnn: the CNN baseline, trained "
        "in image space; with --kind rigid: rt_nerf, rt_nerf_no_pose, rp_nerf); overrides the preset",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="run folder (default: runs/<subject>-<model>, runs/<kind>-<model>)"
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set train.steps=5000 (repeatable)",
    )
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the checkpoint in --out (--set may raise train.steps, change its anneal or how often it writes)",
    )
    parser.add_argument(
        "--max-minutes", type=positive_number, default=None, help="stop (and checkpoint) after this many minutes"
    )
    parser.add_argument(
        "--smpl-dir",
        default=None,
        help="SMPL model folder or file (default: $NARF_SMPL_DIR, else the generated stand-in)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from pipelines.runs.fit import fit
    from pipelines.runs.requests import FitInterrupted, FitRequest

    request = FitRequest(
        out=args.out,
        preset=args.config,
        kind=args.kind or LEGACY_KINDS.get(args.dataset),
        model=args.model,
        subject=args.subject,
        data_root=args.data_root,
        overrides=tuple(args.overrides),
        resume=args.resume,
        max_minutes=args.max_minutes,
        device=args.device,
        progress=not args.quiet,
        smpl_dir=args.smpl_dir,
    )
    try:
        outcome = fit(request, announce=lambda line: print(f"narf-fit: {line}", file=sys.stderr))
    except FitInterrupted as stop:
        print(
            f"narf-fit: interrupted at step {stop.step}; checkpoint saved, continue with "
            f"narf-fit --out {stop.run_dir} --resume",
            file=sys.stderr,
        )
        return 130
    if outcome.main_process:
        state = "finished" if outcome.finished else "stopped (resume with --resume)"
        print(
            f"narf-fit: {state} at step {outcome.step}, training PSNR {outcome.psnr:.2f} dB; run folder "
            f"{outcome.run_dir}"
        )
        if outcome.kept is not None and outcome.kept[0] >= 0:
            step, score = outcome.kept
            print(f"narf-fit: evaluation uses the weights of step {step} (held-back frames {score:.2f} dB)")
    return 0


def entrypoint() -> None:
    sys.exit(run_cli("narf-fit", main))


if __name__ == "__main__":  # torchrun -m pipelines.cli.fit ...
    entrypoint()
