"""``make gpu-real``: the real demo's capture on a lent GPU, in one call (docs/guides/speed.md, *On a GPU*).

A lent GPU machine takes a working tree of at most 64 MiB and a few minutes, so this is two commands:

* ``pack CAPTURE OUT`` (here): a copy of a prepared capture small enough to travel. Every pixel that the loader
  sets to the background (outside the mask and its boundary band, docs/formats.md §1) is black already, with a
  margin for the undistortion's and the resize's neighbours, and the image is written again as JPEG; the overlay
  folder stays behind. ``check`` reports how far the loaded views of the copy are from the original's.
* ``run --subject OUT`` (there): (1) rays/s of the paper preset in fp32, TF32 and bf16, and bf16 without
  deterministic kernels (``--precisions``: also with torch.compile), each fitted alone for a few seconds, and a
  profile of a few more steps (:func:`profile`: where a step's time goes); (2) by default ``paper_sparse`` (the
  CPU preset's levers on the paper's network; docs/results/real-capture.md, *The real demo on a GPU*) alone, with
  the colour's left-right symmetry, and with the symmetry and the pose correction, all in bf16 (``--variants``:
  the paper preset and other precisions too), fitted side by side for the same time (or ``--steps``), then
  ``narf-eval`` on the training images, the held-out camera and novel poses. Figures go to one JSON file after each
  stage, so what was measured comes back even if the call is cut short.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

#: The fits of stage 2: name -> (preset, config overrides); ``cpu_levers_tf32`` is ``paper_sparse``, the paper
#: preset with the CPU preset's colour, shells and anneal; ``mirror_bf16_nondet`` adds the CPU preset's left-right
#: symmetry of the colour (docs/model.md §6).
VARIANTS = {
    "paper_fp32": ("paper", ["train.precision=fp32"]),
    "paper_tf32": ("paper", ["train.precision=tf32"]),
    "paper_bf16_nondet": ("paper", ["train.precision=bf16", "train.deterministic=false"]),
    "pose_correction_tf32": ("paper", ["train.precision=tf32", "train.pose_correction=true"]),
    "cpu_levers_tf32": ("paper_sparse", ["train.precision=tf32"]),
    "cpu_levers_fp32": ("paper_sparse", ["train.precision=fp32"]),
    "cpu_levers_bf16_nondet": ("paper_sparse", ["train.precision=bf16", "train.deterministic=false"]),
    "mirror_bf16_nondet": (
        "paper_sparse",
        ["train.precision=bf16", "train.deterministic=false", "train.mirror_weight=0.1"],
    ),
    "mirror_pose_bf16_nondet": (
        "paper_sparse",
        ["train.precision=bf16", "train.deterministic=false", "train.mirror_weight=0.1", "train.pose_correction=true"],
    ),
}
#: Stage 1's suffixes: ``bf16+compile+nondet`` is bf16 with these overrides.
SPEED_SUFFIXES = {"compile": "train.compile=true", "nondet": "train.deterministic=false"}
SPLITS = ("same_pose_same_view", "novel_view", "novel_pose")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m bench.gpu_real", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    pack = sub.add_parser("pack", help="a copy of CAPTURE small enough to travel")
    pack.add_argument("capture", type=Path)
    pack.add_argument("out", type=Path)
    pack.add_argument("--quality", type=int, default=95, help="JPEG quality of the images")
    pack.add_argument("--margin", type=int, default=12, help="pixels kept beyond the mask and its band")
    pack.add_argument(
        "--drop",
        default="mask",
        help="folders left behind besides overlay (default: mask, which a fit with data.mask_source=cihp never reads)",
    )
    check = sub.add_parser("check", help="the loaded views of a packed copy against the original's")
    check.add_argument("capture", type=Path)
    check.add_argument("packed", type=Path)
    run = sub.add_parser("run", help="the measurements, on the GPU")
    run.add_argument("--subject", type=Path, required=True, help="a prepared (packed) capture")
    run.add_argument("--work", type=Path, default=Path("runs/gpu-real"), help="folder of the runs")
    run.add_argument("--out", type=Path, default=None, help="JSON of the figures (default: WORK/gpu-real.json)")
    run.add_argument("--speed-seconds", type=float, default=15.0, help="stage 1: seconds of fitting per precision")
    run.add_argument(
        "--precisions",
        default="fp32,tf32,bf16,bf16+nondet",
        help="stage 1: the precisions timed; +compile adds train.compile=true (torch.compile), +nondet "
        "train.deterministic=false (atomic index_add / scatter kernels on CUDA)",
    )
    run.add_argument("--compile-seconds", type=float, default=90.0, help="stage 1: extra seconds for a compile")
    run.add_argument("--profile", default="bf16", help="stage 1: precisions profiled after their timing")
    run.add_argument("--profile-steps", type=int, default=10, help="stage 1: steps profiled")
    run.add_argument(
        "--fit-seconds",
        type=float,
        default=300.0,
        help="stage 2: each fit's time, side by side (with --steps: its cap)",
    )
    run.add_argument("--steps", type=int, default=0, help="stage 2: steps per fit instead (0: --fit-seconds)")
    run.add_argument("--limit", type=int, default=8, help="views evaluated per split")
    run.add_argument(
        "--variants",
        default="cpu_levers_bf16_nondet,mirror_bf16_nondet,mirror_pose_bf16_nondet",
        help=f"stage 2's fits, comma-separated, of {', '.join(VARIANTS)} (four at once outgrew an H200's 141 GB)",
    )
    run.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    run.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="an override of every fit")
    return parser


def pack(capture: Path, out: Path, quality: int, margin: int, drop: set[str]) -> None:
    """Copy ``capture`` to ``out`` without its overlay and the folders ``drop``, each image blacked out beyond its
    masks (every mask folder), their band and ``margin`` pixels, and written again as JPEG."""
    import cv2

    from pipelines.datasets.capture import ZjuCapture
    from pipelines.datasets.errors import CaptureError
    from pipelines.datasets.images import read_image
    from pipelines.datasets.zju_mocap import boundary_band

    if out.exists():
        raise CaptureError(f"{out}: exists; remove it first")
    source = ZjuCapture(capture, ratio=1.0)
    image_dirs = {Path(rel).parts[0] for row in source.ims for rel in row}
    shutil.copytree(
        capture,
        out,
        ignore=lambda d, names: [n for n in names if Path(d) == capture and n in image_dirs | drop | {"overlay"}],
    )
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    for rel in tqdm([rel for row in source.ims for rel in row], desc="pack", unit="view"):
        bgr = read_image(capture / rel)
        keep = np.zeros(bgr.shape[:2], bool)
        for folder in ("mask", "mask_cihp", "mask_unknown"):
            path = capture / folder / Path(rel).with_suffix(".png")
            if path.is_file():
                keep |= read_image(path, cv2.IMREAD_GRAYSCALE, "mask") != 0
        keep = cv2.dilate((keep | boundary_band(keep)).astype(np.uint8), kernel) > 0
        bgr[~keep] = 0
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(out / rel), bgr, [cv2.IMWRITE_JPEG_QUALITY, quality]):
            raise CaptureError(f"{out / rel}: could not be written")


def check(capture: Path, packed: Path) -> dict:
    """Every view of both captures as the fit loads it (ratio 0.5, the cihp masks): the packed copy's PSNR over the
    mask's pixels and over the whole image, against the original's, and whether the masks are the same."""
    from pipelines.datasets.capture import ZjuCapture

    original, copy = ZjuCapture(capture), ZjuCapture(packed)
    worst_person, squared, person, pixels, masks_equal = np.inf, 0.0, 0.0, 0, True
    views = [(frame, cam) for frame in range(original.n_frames) for cam in range(original.n_cameras)]
    for frame, cam in tqdm(views, desc="check", unit="view"):
        a, b = original.load_frame(frame, cam), copy.load_frame(frame, cam)
        masks_equal &= bool(np.array_equal(a.mask, b.mask))
        error = (a.image - b.image) ** 2
        inside = a.mask > 0
        mse = float(error[inside].mean()) if inside.any() else 0.0
        worst_person = min(worst_person, -10 * np.log10(max(mse, 1e-12)))
        squared, person, pixels = (
            squared + float(error.sum()),
            person + float(error[inside].sum()),
            pixels + int(inside.sum()),
        )
    n = len(views)
    whole = squared / (n * a.image.size)
    return {
        "views": n,
        "masks_equal": masks_equal,
        "person_psnr": round(-10 * np.log10(max(person / (3 * pixels), 1e-12)), 2),
        "worst_view_person_psnr": round(worst_person, 2),
        "full_psnr": round(-10 * np.log10(max(whole, 1e-12)), 2),
    }


def _write(path: Path, figures: dict) -> None:
    from fitting.files import atomic_write_text

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(figures, indent=1))


def speed_overrides(name: str) -> list[str]:
    """Stage 1's config overrides of a precision name such as ``bf16+compile+nondet``; ValueError if it is not fp32,
    tf32 or bf16 with suffixes of SPEED_SUFFIXES."""
    precision, *suffixes = name.split("+")
    if precision not in ("fp32", "tf32", "bf16") or not set(suffixes) <= set(SPEED_SUFFIXES):
        raise ValueError(f"--precisions: {name} is not fp32, tf32 or bf16 with +{' or +'.join(SPEED_SUFFIXES)}")
    return [f"train.precision={precision}", *(SPEED_SUFFIXES[suffix] for suffix in suffixes)]


def speed(subject: Path, work: Path, device, extra: list[str], args: argparse.Namespace, publish) -> dict:
    """Stage 1: each of ``args.precisions``' rays/s (median of the log's rows after the first) and peak memory,
    fitted alone for ``args.speed_seconds`` (and ``args.compile_seconds`` more where torch.compile runs first); those
    in ``args.profile`` then run ``args.profile_steps`` more steps under the profiler (:func:`profile`). Each one's
    figures go to ``publish`` as soon as they are known."""
    import torch

    from bench.gpu_check import log_rows, peak_gpu_memory_gib, rays_per_s
    from fitting.config import load_config
    from fitting.run_folder import prepare_run_dir
    from pipelines.runs.fit import start_run

    rates, profiled = {}, set(args.profile.split(","))
    for name in filter(None, args.precisions.split(",")):
        compiled = "compile" in name.split("+")
        overrides = [f"data.subject={subject}", "train.validate_every=0", "train.log_every=10", *extra]
        overrides += speed_overrides(name)
        config = load_config("paper", overrides)
        seconds = args.speed_seconds + (args.compile_seconds if compiled else 0.0)
        folder = work / f"speed_{name.replace('+', '_')}"
        shutil.rmtree(folder, ignore_errors=True)  # the tool's own folder: a rerun starts afresh
        run = prepare_run_dir(folder, False)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        started = time.perf_counter()
        trainer = start_run(run, device, config, progress=False)
        ready = time.perf_counter()
        result = trainer.fit(max_minutes=seconds / 60)
        rows = log_rows(run)
        rates[name] = {
            "steps": result.step,
            "rays_per_s": rays_per_s(rows, result.step, trainer, skip=1),  # the first row holds the warm-up
            "start_s": round(ready - started, 1),
            "train_psnr_last": round(rows[-1]["psnr"], 2) if rows else None,
            "peak_gpu_memory_gib": peak_gpu_memory_gib(device),
        }
        if name in profiled:
            rates[name]["profile"] = profile(trainer, args.profile_steps, device)
        del trainer
        if device.type == "cuda":
            torch.cuda.empty_cache()
        publish(rates)
        print(f"gpu-real: speed {name}: {rates[name]}", flush=True)
    return rates


def profile(trainer, steps: int, device) -> dict:
    """``steps`` more training steps under ``torch.profiler``: per step, the wall time, the time of each of the
    trainer's named ranges (``narf.sample``, ``narf.forward``, ``narf.backward``: CPU time to launch them) and the
    operators that take the most device time (self time, so the rows add up), with their calls."""
    import torch
    from torch.profiler import ProfilerActivity

    cuda = device.type == "cuda"
    activities = [ProfilerActivity.CPU, *([ProfilerActivity.CUDA] if cuda else [])]
    with torch.profiler.profile(activities=activities) as prof:
        started = time.perf_counter()
        for _ in range(steps):
            trainer.train_step()
        if cuda:
            torch.cuda.synchronize(device)
        wall = time.perf_counter() - started
    events = prof.key_averages()
    self_time = (lambda e: e.self_device_time_total) if cuda else (lambda e: e.self_cpu_time_total)
    ranges = {e.key: round(e.cpu_time_total / 1e3 / steps, 2) for e in events if e.key.startswith("narf.")}
    top = sorted((e for e in events if not e.key.startswith("narf.")), key=self_time, reverse=True)[:40]
    # the kernels and copies alone (the operators' own device time counts their kernels a second time)
    busy = sum(e.self_device_time_total for e in events if e.device_type == torch.autograd.DeviceType.CUDA)
    return {
        "steps": steps,
        "wall_ms_per_step": round(1e3 * wall / steps, 1),
        "ranges_cpu_ms_per_step": ranges,
        "device_ms_per_step": round(sum(self_time(e) for e in events) / 1e3 / steps, 1),
        "gpu_busy_ms_per_step": round(busy / 1e3 / steps, 1) if cuda else None,
        "operators_per_step": round(sum(e.count for e in events if not e.key.startswith("narf.")) / steps),
        "top": [
            {"op": e.key, "ms_per_step": round(self_time(e) / 1e3 / steps, 2), "calls_per_step": e.count / steps}
            for e in top
        ],
    }


def steps_for(rates: dict, variants: list[str], seconds: float, rays_per_step: int) -> int:
    """The steps each variant reaches when they run side by side for ``seconds``, if each step of a variant costs
    what it cost alone at its precision (no gain from sharing the GPU assumed)."""
    cost = 0.0
    for name in variants:
        rate = rates[speed_name(VARIANTS[name][1], rates)]["rays_per_s"]
        cost += rays_per_step / max(rate or 1, 1)
    return max(10, round(seconds / cost))


def speed_name(overrides: list[str], timed) -> str:
    """The stage-1 run of ``timed`` (its names, or its rates keyed by name) that times a variant of ``overrides``:
    its precision with the suffixes whose overrides it carries (``bf16+nondet`` for bf16 without deterministic
    kernels), else its precision alone; KeyError if stage 1 timed neither."""
    precision = next(o.split("=")[1] for o in overrides if o.startswith("train.precision="))
    suffixes = [suffix for suffix, override in SPEED_SUFFIXES.items() if override in overrides]
    for name in ("+".join([precision, *suffixes]), precision):
        if name in timed:
            return name
    raise KeyError(f"stage 1 timed no {precision} run for the variant's overrides {overrides}")


def _person(split: dict) -> dict:
    """A split's figures as the results tables give them: person PSNR, NB crop PSNR / SSIM, silhouette pixels."""
    crop = split["nb_crop"]
    return {
        "views": split["n_views"],
        "person_psnr": round(crop["breakdown"]["psnr_person"], 2),
        "nb_psnr": round(crop["psnr"], 2),
        "nb_ssim": round(crop["ssim"], 3),
        "silhouette_pct": round(100 * crop["breakdown"]["pixels_silhouette"], 2),
        "full_psnr": round(split["full"]["psnr"], 2),
    }


def side_by_side(
    subject: Path, work: Path, variants: list[str], budget: list[str], limit: int, extra: list[str], out
) -> dict:
    """Stage 2: the variants fitted at once (one process each, ``narf-fit`` with the arguments ``budget``), each
    evaluated as soon as it ends; returns each one's steps, time and split figures (also passed to ``out``)."""
    launched = {}
    for name in variants:
        run = work / name
        shutil.rmtree(run, ignore_errors=True)
        preset, overrides = VARIANTS[name]
        sets = [a for o in ["train.validate_every=0", *extra, *overrides] for a in ("--set", o)]
        fit = [sys.executable, "-m", "pipelines.cli.fit", "--subject", str(subject), "--config", preset]
        fit += ["--out", str(run), "--quiet", *budget, *sets]
        evaluate = [sys.executable, "-m", "pipelines.cli.eval", "--run", str(run), "--limit", str(limit)]
        evaluate += [a for s in SPLITS for a in ("--split", s)] + ["--grids", "0", "--quiet"]
        script = f"{shlex.join(fit)} && {shlex.join(evaluate)}"
        log = open(work / f"{name}.log", "w")
        threads = {"OMP_NUM_THREADS": str(max(1, (os.cpu_count() or 1) // len(variants)))}
        launched[name] = (
            subprocess.Popen(
                ["bash", "-c", script], stdout=log, stderr=subprocess.STDOUT, env={**os.environ, **threads}
            ),
            time.perf_counter(),
            log,
        )
    figures = {}
    for name, (process, started, log) in launched.items():
        code = process.wait()
        log.close()
        run = work / name
        preset, overrides = VARIANTS[name]
        entry = {
            "exit": code,
            "wall_s": round(time.perf_counter() - started, 1),
            "preset": preset,
            "overrides": overrides,
        }
        metrics = run / "eval" / "metrics.json"
        if code == 0 and metrics.is_file():
            data = json.loads(metrics.read_text())
            entry["steps"] = data["step"]
            entry.update({s: _person(data["splits"][s]) for s in SPLITS})
        else:
            entry["log_tail"] = (work / f"{name}.log").read_text()[-1500:]
        figures[name] = entry
        out(figures)
        print(f"gpu-real: {name}: {entry}", flush=True)
    return figures


def _variants(args: argparse.Namespace) -> list[str]:
    """Stage 2's variants, checked before any work: known names, and a budget stage 2 can size."""
    variants = [v for v in args.variants.split(",") if v]
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        raise ValueError(f"--variants: unknown {', '.join(unknown)}; known: {', '.join(VARIANTS)}")
    timed = [name for name in args.precisions.split(",") if name]
    for name in timed:
        speed_overrides(name)
    if variants and not args.steps and args.speed_seconds <= 0:
        raise ValueError("--fit-seconds sizes the pose correction's start from stage 1's rates: give --steps instead")
    if variants and not args.steps:  # each variant's rate must come from stage 1, before the GPU's time is spent
        for name in variants:
            try:
                speed_name(VARIANTS[name][1], timed)
            except KeyError as error:
                raise ValueError(
                    f"--variants {name}: {error.args[0]}; add it to --precisions or give --steps"
                ) from None
    return variants


def run(args: argparse.Namespace) -> int:
    import torch

    from fitting.run_folder import auto_device

    device = auto_device(args.device)
    variants = _variants(args)
    subject, work = args.subject.resolve(), args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    out = args.out or work / "gpu-real.json"
    figures = {
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "torch": torch.__version__,
    }
    figures["subject"] = str(args.subject)
    started = time.perf_counter()
    if args.speed_seconds > 0:
        publish = lambda part: _write(out, {**figures, "speed": part})  # noqa: E731
        figures["speed"] = speed(subject, work, device, args.set, args, publish)
        figures["speed_stage_s"] = round(time.perf_counter() - started, 1)
        _write(out, figures)
    if variants:
        from fitting.config import load_config

        rays_per_step = (lambda t: t.images_per_step * t.rays_per_image)(load_config("paper", []).train)
        if args.steps:  # the steps, with --fit-seconds as a cap, so a slow fit still leaves time to evaluate
            budget, expected = (
                ["--set", f"train.steps={args.steps}", "--max-minutes", str(args.fit_seconds / 60)],
                args.steps,
            )
        else:
            budget = ["--max-minutes", str(args.fit_seconds / 60)]
            expected = steps_for(figures["speed"], variants, args.fit_seconds, rays_per_step)
        # the pose correction starts once the field has taken shape: at 40 % of the steps (docs/model.md §6)
        extra = [*args.set, f"train.pose_start={max(1, 2 * expected // 5)}"]
        figures["side_by_side_budget"] = {"arguments": budget, "expected_steps": expected, "overrides": extra}
        _write(out, figures)
        publish = lambda part: _write(out, {**figures, "side_by_side": part})  # noqa: E731
        figures["side_by_side"] = side_by_side(subject, work, variants, budget, args.limit, extra, publish)
    figures["total_s"] = round(time.perf_counter() - started, 1)
    _write(out, figures)
    print("gpu-real: " + json.dumps(figures), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "pack":
        pack(args.capture, args.out, args.quality, args.margin, {"overlay", *filter(None, args.drop.split(","))})
        return 0
    if args.command == "check":
        print(json.dumps(check(args.capture, args.packed), indent=1))
        return 0
    return run(args)


if __name__ == "__main__":
    from pipelines.cli.common import run_cli

    sys.exit(run_cli("python -m bench.gpu_real", main))  # a known error: one line and exit code 2
