"""``narf-fit``: fit an avatar to one subject (synthetic stand-in when no real capture is found), or train the
autoencoder across people on a THUman-layout set (``--dataset thuman``)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from pipelines.cli.common import HelpFormatter, run_cli

#: Settings that ``--resume`` may change (``--set``): how long to go on and how often to write.
RESUMABLE = {"train.steps", "train.checkpoint_minutes", "train.validate_every", "train.log_every"}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="narf-fit",
        description="Fit a NARF avatar (default NARF_D) to a multi-view capture in the ZJU-MoCap layout, or with "
        "--dataset thuman train the NARF autoencoder (image encoder + latent-conditioned field) across the people of "
        "a THUman render_128 set (--data-root: the set's folder; default: the synthetic stand-in), or with --dataset "
        "rigid fit a rigid-object model (RT-NeRF, RT-NeRF w/o xi, RP-NeRF; supplement Table B). Writes "
        "config.yaml, checkpoint.pt (atomic, every few minutes and at the end), log.jsonl, curve.png and val/ "
        "renders into --out. A killed fit resumes with --resume and ends where an uninterrupted one would.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument(
        "--dataset",
        choices=("zju", "thuman", "rigid"),
        default=None,
        help="zju: one subject (default); thuman: the autoencoder across people (presets ae_cpu / ae_paper; "
        "--model p_nerf and narf_h train at lr 0.001 there, as in the supplement); rigid: one rigid object "
        "(presets rigid_cpu / rigid_paper; --data-root: the set, default the synthetic stand-in)",
    )
    parser.add_argument("--subject", default=None, help="subject name or folder (default from the preset: taichi)")
    parser.add_argument("--data-root", default=None, help="data root (default: $NARF_DATA or data/)")
    parser.add_argument(
        "--config",
        default=None,
        help="preset name (cpu, paper, tiny, cnn, ae_cpu, ae_paper, ae_tiny, ae_cnn, ae_cnn_paper, rigid_cpu, "
        "rigid_paper, rigid_tiny) or YAML file; default: cnn for --model cnn, ae_paper / ae_cpu for --dataset thuman "
        "(ae_cnn_paper / ae_cnn with --model cnn), rigid_paper / rigid_cpu for --dataset rigid, else paper with CUDA "
        "and cpu without",
    )
    parser.add_argument(
        "--model",
        default=None,
        help="model name (narf_d, narf_d_sigmoid, narf_h, narf_p, p_nerf, "
        "d_narf, or cnn: the CNN baseline, trained in image space; --dataset rigid: rt_nerf, rt_nerf_no_pose, "
        "rp_nerf); overrides the preset",
    )
    parser.add_argument("--out", type=Path, default=None, help="run folder (default: runs/<subject>-<model>)")
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
        help="continue the checkpoint in --out (--set may raise train.steps or change how often it writes)",
    )
    parser.add_argument("--max-minutes", type=float, default=None, help="stop (and checkpoint) after this long")
    parser.add_argument(
        "--smpl-dir",
        default=None,
        help="SMPL model folder or file (default: $NARF_SMPL_DIR, else the generated stand-in)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import torch

    from fitting.checkpoint import load_checkpoint
    from fitting.distributed import barrier, from_environment, shutdown
    from fitting.trainer import auto_device, prepare_run_dir

    if args.smpl_dir:
        os.environ["NARF_SMPL_DIR"] = args.smpl_dir
    device = auto_device(args.device)
    processes = from_environment(device)
    if processes.distributed and device.type == "cuda":
        device = torch.device("cuda", processes.local_rank)
    config = _config(args, device)
    name = config.data.dataset if config is not None and config.data.dataset in ("thuman", "rigid") else None
    out = args.out or Path("runs") / f"{name or Path(config.data.subject).name}-{config.model.name}"
    if args.resume and not (Path(out) / "checkpoint.pt").exists():
        raise FileNotFoundError(f"{out}: no checkpoint to resume")
    run_dir = prepare_run_dir(out, config, args.resume, write=processes.is_main)
    barrier(processes)
    trainer = _start(args, config, run_dir, device, processes, load_checkpoint(run_dir) if args.resume else None)
    size = (
        f"{trainer.config.model.image_size}^2"
        if trainer.config.model.name == "cnn"
        else f"width {trainer.config.model.width}"
    )
    scale = f", {processes.world_size} processes" if processes.distributed else ""
    if processes.is_main:
        print(
            f"narf-fit: {trainer.config.model.name} ({size}) on "
            f"{trainer.fit_data.description}, device {device}{scale}, torch {torch.__version__}",
            file=sys.stderr,
        )
    try:
        result = trainer.fit(args.max_minutes)
    except KeyboardInterrupt:  # the trainer has saved a checkpoint on its way out
        print(
            f"narf-fit: interrupted at step {trainer.step}; checkpoint saved, continue with "
            f"narf-fit --out {run_dir} --resume",
            file=sys.stderr,
        )
        return 130
    state = "finished" if result.finished else "stopped (resume with --resume)"
    if processes.is_main:
        print(f"narf-fit: {state} at step {result.step}, training PSNR {result.psnr:.2f} dB; run folder {run_dir}")
    shutdown(processes)
    return 0


def _config(args: argparse.Namespace, device):
    """The run's config from the preset (the device's default unless ``--config``) and the overrides; None when
    resuming, which keeps the saved one (only the ``RESUMABLE`` keys may be set again)."""
    from fitting.config import load_config

    overrides = list(args.overrides)
    if args.subject:
        overrides.insert(0, f"data.subject={args.subject}")
    if args.data_root:
        if not Path(args.data_root).is_dir():
            raise FileNotFoundError(f"{args.data_root}: no such data root folder")
        overrides.insert(0, f"data.data_root={args.data_root}")
    if args.model:
        overrides.insert(0, f"model.name={args.model}")
    if args.dataset:
        overrides.insert(0, f"data.dataset={args.dataset}")
    if args.dataset == "thuman" and args.model in ("p_nerf", "narf_h"):
        overrides.insert(0, "train.lr=0.001")  # the supplement's exception for these two autoencoders (§F)
    if args.resume:
        if args.out is None:
            raise ValueError("--resume needs --out (the run folder to continue)")
        changed = sorted({o.split("=", 1)[0].strip() for o in args.overrides} - RESUMABLE)
        if changed or args.subject or args.data_root or args.model or args.dataset or args.config:
            raise ValueError(
                f"--resume continues the run as it was configured; only --set {', '.join(sorted(RESUMABLE))} may "
                f"change (got {', '.join(changed) or 'a preset, model, subject, dataset or data root'})"
            )
        return None
    gpu = device.type == "cuda"
    if args.dataset == "thuman":
        default = ("ae_cnn_paper" if gpu else "ae_cnn") if args.model == "cnn" else "ae_paper" if gpu else "ae_cpu"
    elif args.dataset == "rigid":
        default = "rigid_paper" if gpu else "rigid_cpu"
    else:
        default = "cnn" if args.model == "cnn" else "paper" if gpu else "cpu"
    return load_config(args.config or default, overrides)


def _start(args: argparse.Namespace, config, run_dir: Path, device, processes, saved: dict | None):
    """The trainer of the run's kind (per subject, autoencoder or rigid object), new or resumed from ``saved``."""
    from pipelines.autoencoder_session import start_autoencoder
    from pipelines.fit_session import start_trainer
    from pipelines.rigid_session import start_rigid

    kind = saved.get("kind") if saved else config.data.dataset
    dataset = saved["config"].get("data", {}).get("dataset") if saved else config.data.dataset
    if kind in ("autoencoder", "thuman"):
        if processes.distributed:
            raise ValueError(
                "data-parallel fitting (torchrun) covers per-subject fits; train the autoencoder as one process"
            )
        return start_autoencoder(config, run_dir, device, args.resume, not args.quiet, args.overrides)
    if dataset == "rigid":
        if processes.distributed:
            raise ValueError("data-parallel fitting (torchrun) covers bodies; fit a rigid object in one process")
        return start_rigid(config, run_dir, device, args.resume, not args.quiet, args.overrides)
    return start_trainer(config, run_dir, device, args.resume, not args.quiet, processes, args.overrides)


def entrypoint() -> None:
    sys.exit(run_cli("narf-fit", main))


if __name__ == "__main__":  # torchrun -m pipelines.cli.fit ...
    entrypoint()
