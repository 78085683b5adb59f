"""Autoencoder training throughput at the CPU default (preset ae_cpu) and at paper size (ae_paper), on a small
THUman-like set generated for the benchmark: rays/s and images/s of full steps (encoder forward/backward on the
step's images, coarse + importance samples, loss, Adam), and the generation time of the stand-in sets at their
default size (which ``narf-synth --dataset thuman|surreal`` writes)."""

from __future__ import annotations

import resource
import tempfile
import time
from pathlib import Path

import torch

from fitting.config import load_config
from fitting.run_folder import prepare_run_dir
from pipelines.runs.fit import start_run
from pipelines.synthetic.surreal import SurrealSynthConfig, generate_surreal
from pipelines.synthetic.thuman import ThumanSynthConfig, generate_thuman

STEPS = {"ae_cpu": 12, "ae_paper": 3}


def _throughput(root: Path, preset: str) -> dict:
    config = load_config(preset, [f"data.data_root={root}", "train.validate_every=0"])
    trainer = start_run(prepare_run_dir(root.parent / preset, False), "cpu", config, progress=False)
    trainer.train_step()  # warm-up
    start = time.perf_counter()
    for _ in range(STEPS[preset]):
        trainer.train_step()
    seconds = (time.perf_counter() - start) / STEPS[preset]
    t = config.train
    return {
        "benchmark": f"autoencoder training ({preset})",
        "setting": f"{config.model.name} width {config.model.width}, latent {config.model.latent_dim}, encoder "
        f"c={config.model.encoder_channels}, {t.images_per_step} images x {t.rays_per_image} rays, "
        f"{config.render.train_coarse}+{config.render.train_fine} samples",
        "value": f"{t.images_per_step * t.rays_per_image / seconds:,.0f} rays/s, "
        f"{t.images_per_step / seconds:.1f} images/s ({seconds:.2f} s/step)",
    }


def run() -> list[dict]:
    torch.set_num_threads(2)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, generate, config in (
            ("thuman", generate_thuman, ThumanSynthConfig()),
            ("surreal", generate_surreal, SurrealSynthConfig()),
        ):
            start = time.perf_counter()
            out = generate(Path(tmp) / name, config, progress=False)
            size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file()) / 1e6
            rows.append(
                {
                    "benchmark": f"narf-synth --dataset {name}",
                    "setting": "default size",
                    "value": f"{time.perf_counter() - start:.0f} s, {size:.0f} MB",
                }
            )
        for preset in STEPS:
            rows.append(_throughput(Path(tmp) / "thuman", preset))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rows[-1]["peak RSS"] = f"{peak:.0f} MB"
    return rows
