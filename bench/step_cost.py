"""The cost of a training step: ``python -m bench.step_cost --subject CAPTURE [NAME=OVERRIDE,OVERRIDE ...]``.

For each variant (a name and its config overrides on ``--preset``; ``render=alone`` renders each of a step's ray
sets by a call of its own, as the fit did before; ``draw=exact`` draws the rays' pixels from each view's pools listed
in full, ``fitting.data.pool_pixels_exact``, as the fit did before) a fit of the capture is started; the fits are
warmed up, then stepped in turn over ``--steps`` steps each (the median step: on a shared machine whose speed drifts,
the variants are slowed alike), and their operators are counted over a few more steps under ``torch.profiler`` (each
operator launch costs a roughly fixed time on a CPU, and a GPU's kernel launches follow them). Prints one Markdown
row per variant: milliseconds a step, rays a second of the training rays, operators a step
(docs/results/benchmark.md, *The step's renders in one call*).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from unittest import mock


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m bench.step_cost", description=__doc__)
    parser.add_argument("variants", nargs="*", help="NAME=KEY=VALUE,KEY=VALUE (default: the preset as it is)")
    parser.add_argument("--subject", type=Path, required=True, help="a prepared capture (narf-prepare-capture)")
    parser.add_argument("--preset", default="cpu", help="the config preset (default: cpu)")
    parser.add_argument("--steps", type=int, default=30, help="timed steps a variant (default: 30)")
    parser.add_argument("--warmup", type=int, default=5, help="steps before the timing (default: 5)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (default: torch's own)")
    return parser


PATCHES = ("render=alone", "draw=exact")  # not config overrides: the step's code as it was before (see above)


def _rendering(overrides: list[str]):
    """The context a variant's steps run in: with ``render=alone``, each ray set by a call of its own; with
    ``draw=exact``, the pixels drawn from pools listed in full."""
    from fitting.data import pool_pixels_exact
    from fitting.training_rays import render_each_set

    context = ExitStack()
    if "render=alone" in overrides:
        context.enter_context(mock.patch("fitting.trainer.render_ray_sets", render_each_set))
    if "draw=exact" in overrides:
        context.enter_context(mock.patch("fitting.data.pool_pixels", pool_pixels_exact))
    return context


def step_costs(subject: Path, preset: str, variants: dict[str, list[str]], steps: int, warmup: int) -> dict:
    """Each variant's median step (ms), training rays/s at that step and operators a step (over 3 profiled steps).
    The variants' fits are built first and then stepped in turn, one step each, so that a machine whose speed
    drifts (a shared one) slows them alike. The override ``render=alone`` renders each ray set of a step by a call
    of its own (as before ``fitting.training_rays.render_ray_sets``), ``draw=exact`` draws from pools listed in full."""
    import torch

    from fitting.config import load_config
    from fitting.run_folder import prepare_run_dir
    from pipelines.runs.fit import start_run

    base = [f"data.subject={subject}", "train.validate_every=0", "train.holdout_every=0"]
    trainers, times, folder = {}, {}, tempfile.TemporaryDirectory()
    with folder:
        for name, overrides in variants.items():
            config = load_config(preset, [*base, *(o for o in overrides if o not in PATCHES)])
            run = prepare_run_dir(Path(folder.name) / name, False)
            trainers[name], times[name] = start_run(run, torch.device("cpu"), config, progress=False), []
        for step in range(warmup + steps):
            for name, trainer in trainers.items():
                with _rendering(variants[name]):
                    started = time.perf_counter()
                    trainer.train_step()
                    if step >= warmup:
                        times[name].append(time.perf_counter() - started)
        costs = {}
        for name, trainer in trainers.items():
            with _rendering(variants[name]):
                with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
                    for _ in range(3):
                        trainer.train_step()
            operators = sum(e.count for e in prof.key_averages() if not e.key.startswith("narf.")) / 3
            median, train = statistics.median(times[name]), trainer.config.train
            rays = train.images_per_step * train.rays_per_image
            costs[name] = {
                "ms": round(1e3 * median, 1),
                "rays_per_s": round(rays / median),
                "operators": round(operators),
            }
    return costs


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if not (args.subject / "annots.npy").is_file():
        print(f"bench.step_cost: {args.subject}: no annots.npy (not a prepared capture)", file=sys.stderr)
        return 2
    from pipelines.cli.common import short_openmp_wait

    short_openmp_wait()  # before torch loads libgomp, as the commands do (docs/design.md, "OpenMP workers' wait")
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()
    print(f"| variant ({args.preset}, {threads} threads) | ms / step | training rays / s | operators / step |")
    print("|---|---|---|---|")
    variants = {}
    for variant in args.variants or ["preset="]:
        name, _, overrides = variant.partition("=")
        variants[name] = list(filter(None, overrides.split(",")))
    for name, cost in step_costs(args.subject, args.preset, variants, args.steps, args.warmup).items():
        print(f"| {name} | {cost['ms']} | {cost['rays_per_s']:,} | {cost['operators']:,} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
