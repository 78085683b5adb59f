"""Glue between a rigid-object set on disk (``pipelines.datasets.rigid``) and the fitting package: find the set
(``data.data_root`` when it holds one, else the synthetic stand-in, generated on demand), start (or resume) a
Trainer of a rigid model (RT-NeRF, RT-NeRF w/o xi, RP-NeRF; paper Eqs. 9-11), and evaluate it on the test
images (supplement Table B: Mask L2 x10^4 / PSNR / SSIM over the full image)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from fitting.config import FitConfig
from fitting.data import FitData, TrainingSet
from fitting.evaluate import average_metrics, evaluate_splits, frame_metrics, render_view, spread
from fitting.fitted import SavedRun, load_fitted, read_run
from fitting.plots import grid, save_png, to_numpy
from fitting.trainer import Trainer
from fitting.trainers import trainer_class
from pipelines.datasets.rigid import RigidSet, load_rigid_views, open_rigid
from pipelines.datasets.smpl_files import cache_dir
from pipelines.datasets.subjects import data_root
from pipelines.runs.requests import EvalRequest, refuse_options
from pipelines.synthetic.rigid import RigidSynthConfig, generate_rigid, is_rigid_complete
from pipelines.synthetic.staging import use_stand_in

#: The object's box in its own frame, in units of its radius: a cube that holds the bounding sphere.
BOX_HALF_EXTENT = 1.0


def resolve_rigid(config: FitConfig, quiet: bool = False, generate: bool = True) -> Path:
    """``data.data_root`` when it holds a rigid set (``train/render_*``), else ``<root>/synthetic/rigid`` (the
    stand-in, generated when missing and announced on stderr)."""
    explicit = Path(config.data.data_root) if config.data.data_root else None
    if explicit is not None and any((explicit / "train").glob("render_*")):
        return explicit
    out = data_root(config.data.data_root) / "synthetic" / "rigid"
    make = lambda: generate_rigid(out, RigidSynthConfig(), progress=not quiet)  # noqa: E731
    return use_stand_in(out, "rigid-object set", "rigid", is_rigid_complete, make, quiet, generate)


def rigid_boxes() -> tuple[torch.Tensor, torch.Tensor]:
    """One box, centred on the object origin (docs/model.md §1 with P = 1)."""
    return torch.zeros(1, 3), torch.full((1, 3), BOX_HALF_EXTENT)


def build_rigid_data(config: FitConfig, device, progress: bool = True) -> FitData:
    """Every training image is its own frame (its own object pose); validation renders the first test image."""
    rigid = open_rigid(resolve_rigid(config, quiet=not progress))
    views, poses = load_rigid_views(rigid, "train")
    training = TrainingSet(views, list(range(len(views))), poses, device, store_dir=cache_dir() / "views")

    def validation():
        view, pose = load_rigid_views(rigid, "test", [0])
        return view[0].image, view[0].camera, pose

    return FitData(
        training, rigid_boxes(), list(range(len(views))), validation, f"{rigid.root}: {len(views)} training images"
    )


def start(
    config: FitConfig, run_dir: Path, device, state: dict | None = None, progress: bool = True, processes=None
) -> Trainer:
    """A Trainer of a rigid model; ``state``: the checkpoint it resumes. One process."""
    data = build_rigid_data(config, device, progress)
    return trainer_class(config)(config, run_dir, device, data, state=state, progress=progress)


def evaluate_rigid_run(run: Path | SavedRun, request: EvalRequest) -> dict:
    """Render the test images of a rigid-object run; write ``RUN/eval/metrics.json`` / ``metrics.md`` (split
    ``test``: full-image Mask L2 x10^4 / PSNR / SSIM) and grids (ground truth | render | depth | error). The kind
    table's entry point: options of other kinds are refused."""
    saved = read_run(run)
    run_dir, r = saved.run_dir, request
    options = {"--mesh": r.mesh, "--surreal": r.surreal, "--refine-steps": r.refine_steps, "--capture": r.capture}
    refuse_options(run_dir, "rigid", options, "subject and autoencoder runs")
    subject_only = {"--novel-colour": r.novel_colour, "--samples": r.samples, "--frame-step": r.frame_step}
    refuse_options(run_dir, "rigid", subject_only, "subject runs")
    fitted = load_fitted(saved, r.device, kind="rigid")
    config, field = fitted.config, fitted.field
    rigid: RigidSet = open_rigid(resolve_rigid(config, quiet=True, generate=False))

    def score(split: str) -> dict:
        indices = spread(list(range(rigid.counts[split])), r.limit)
        views, poses = load_rigid_views(rigid, split, indices)
        bg = 1.0 if config.data.white_background else 0.0
        records = []
        for k, view in enumerate(tqdm(views, desc=f"eval {split}", unit="view", disable=not r.progress)):
            pose = poses.select(torch.tensor([k])).to(r.device)
            render = to_numpy(render_view(field, view.camera, pose, config))
            empty = np.zeros(view.mask.shape, bool)
            records.append({"image": indices[k], **frame_metrics(render, view.image, view.mask, empty, bg)})
            if k < r.grids:
                path = run_dir / "eval" / "grids" / split / f"{indices[k]:05d}.png"
                save_png(path, grid(view.image, render, False))
        return {"n_views": len(records), "full": average_metrics(records, "full"), "per_view": records}

    def header() -> dict:
        c = config.model
        return {"run": str(run_dir), "step": fitted.step, "model": c.name, "width": c.width, "dataset": str(rigid.root)}

    return evaluate_splits(run_dir / "eval", ("test",), score, header, markdown_rigid)


def markdown_rigid(report: dict) -> str:
    """Table B layout: one row, Mask L2 (x10^4) / PSNR / SSIM on the test images."""
    m = report["splits"]["test"]["full"]
    return "\n".join(
        [
            f"# {report['model']} (width {report['width']}), step {report['step']}: {report['dataset']}",
            "",
            "| model | test images | Mask L2 (x10^4) | PSNR (dB) | SSIM |",
            "|---|---|---|---|---|",
            f"| {report['model']} | {report['splits']['test']['n_views']} | {m['mask_l2']:.1f} | {m['psnr']:.2f} | "
            f"{m['ssim']:.4f} |",
            "",
        ]
    )
