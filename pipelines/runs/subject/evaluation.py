"""Evaluate a fitted run on its capture's protocol splits (``narf-eval``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from fitting.config import with_eval_samples
from fitting.corrections import camera_response
from fitting.evaluate import (
    average_metrics,
    evaluate_splits,
    frame_metrics,
    markdown_table,
    nb_crop_region,
    render_view,
    spread,
)
from fitting.fitted import SavedRun, read_run
from fitting.plots import grid, save_png, to_numpy
from pipelines.body.locate import file_sha256
from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.errors import CaptureError
from pipelines.runs.requests import EvalRequest, refuse_options
from pipelines.runs.subject.coverage import training_coverage, unseen_pixels
from pipelines.runs.subject.session import (
    borrows_colour,
    capture_body_record,
    capture_gains,
    load_run,
    poses_for_frames,
)

#: the training views whose surfaces the error breakdown counts as seen are at most this many, evenly spread over
#: the training split (docs/model.md §7, *Surfaces the training views saw*): neighbouring frames show nearly the same
#: faces, and a capture of 23 cameras x 300 frames would otherwise take minutes
COVERAGE_VIEWS = 240


def _view_metrics(run, split: str, items, out_dir: Path, request: EvalRequest, coverage: np.ndarray) -> list[dict]:
    """Render every (frame, camera) of ``items`` and score it against the capture (full image and NB crop, whose
    breakdown tells apart the surfaces the training views saw: ``coverage`` (F,), from ``training_coverage``); the
    first ``request.grids`` views also go to ``out_dir/grids/<split>/``. Returns one record per view. The run's own
    capture is posed as the run shows it (corrected training frames); another capture (``run.other``) with its own
    poses."""
    config, field, device = run.config, run.field, request.device
    capture = run.capture if split != "capture" else run.other
    frames = sorted({f for f, _ in items})
    poses, _, _ = poses_for_frames(run if split != "capture" else capture, run.body_model, frames)
    poses = run.colour_poses(poses, frames if split != "capture" else None).to(device)
    bg = 1.0 if config.data.white_background else 0.0
    gains = capture_gains(capture, config)  # each camera's colour (docs/model.md §6)
    records = []
    views = tqdm(items, desc=f"eval {split}", unit="view", disable=not request.progress)
    for index, (frame, cam) in enumerate(views):
        item = capture.load_frame(frame, cam)
        pose = poses.select(torch.tensor([frames.index(frame)], device=device))
        render = to_numpy(render_view(field, item.camera, pose, config))
        if gains is not None:
            render["rgb"] = np.clip(camera_response(render["rgb"], render["mask"], gains[cam], bg), 0.0, 1.0)
        vertices = capture.vertices(frame)
        region = nb_crop_region(item.camera, vertices)
        unseen = unseen_pixels(item.camera, vertices, run.body_model.faces, coverage)
        metrics = frame_metrics(render, item.image, item.mask, region, bg, item.band, unseen)
        records.append({"frame": frame, "camera": cam, **metrics})
        if index < request.grids:
            save_png(out_dir / "grids" / split / f"frame{frame:05d}_cam{cam:02d}.png", grid(item.image, render))
    return records


def _score_split(run, split: str, out_dir: Path, request: EvalRequest, coverage: np.ndarray) -> dict:
    """One split's report: the averages of both protocols, each view's record and, with ``request.mesh``, the
    surface against the true one (``pipelines.runs.subject.mesh.mesh_accuracy``, meshes in ``eval/meshes/``)."""
    if split == "capture":
        every = run.other.protocol()
        items = spread(every.usable(range(run.other.n_frames), range(run.other.n_cameras)), request.limit)
    else:
        items = spread(run.protocol.split(split), request.limit)
    if not items:
        raise ValueError(f"split '{split}' is empty for {run.capture.root} under the {run.protocol.name} protocol")
    records = _view_metrics(run, split, items, out_dir, request, coverage)
    result = {
        "n_views": len(records),
        "limit": request.limit,
        **({} if split == "capture" else {"frame_step": run.protocol.interval}),  # the split's frames: every Nth
        "full": average_metrics(records, "full"),
        "nb_crop": average_metrics(records, "nb_crop"),
        "per_view": records,
        "novel_colour": "nearest" if borrows_colour(run.config) else "own",  # docs/model.md §4
        **({"capture": str(run.other.root)} if split == "capture" else {}),
    }
    if request.mesh:
        from pipelines.runs.subject.mesh import mesh_accuracy

        frames = sorted({f for f, _ in items})
        result["mesh"] = mesh_accuracy(run, frames, out_dir / "meshes" / split, request)
    return result


def evaluate_run(run: Path | SavedRun, request: EvalRequest) -> dict:
    """Evaluate ``request.splits`` of the run's protocol; update ``RUN/eval/metrics.json`` and ``metrics.md`` (the
    kind table's entry point; options of other kinds are refused).

    With ``request.mesh``, also the surface of each split frame that has a true surface (``surfaces/<frame>.ply``).
    ``request.capture``: another prepared capture of the same person, evaluated as split ``capture``
    (:func:`open_other_capture`).
    """
    saved = read_run(run)
    run_dir, r = saved.run_dir, request
    users = "autoencoder runs"
    refuse_options(run_dir, "subject", {"--surreal": r.surreal, "--refine-steps": r.refine_steps}, users)
    if r.capture is not None and (tuple(r.splits) != ("capture",) or r.frame_step is not None):
        raise ValueError("--capture evaluates every frame and camera of the other recording as the split 'capture'")
    loaded = load_run(saved, r.device)
    if r.novel_colour is not None:  # docs/model.md §4, *Colour of frames not trained on*
        model = dataclasses.replace(loaded.config.model, novel_colour=r.novel_colour)
        loaded.config = dataclasses.replace(loaded.config, model=model)
    if r.samples is not None:  # the renders' estimator of the volume integral (docs/model.md §7)
        loaded.config = with_eval_samples(loaded.config, *r.samples)
    if r.frame_step is not None:  # in place of the protocol's every 30th frame (docs/formats.md §1.8)
        loaded.protocol = dataclasses.replace(loaded.protocol, interval=r.frame_step)
    if r.capture is not None:
        loaded.other = open_other_capture(loaded, run_dir, Path(r.capture))
    out_dir = run_dir / "eval"
    config = loaded.config

    def header() -> dict:
        return {
            "run": str(run_dir),
            "step": loaded.step,
            "last_step": loaded.last_step,
            "model": config.model.name,
            "width": config.model.width,
            # the density part blocks' point encoding: frequencies (the paper) or part grids (docs/model.md §2)
            "encoding": config.model.encoding,
            "trunk_blocks": config.model.trunk_blocks,  # the trunk's residual blocks (the paper: 3)
            "shading": config.model.shading,  # albedo under a learned world lighting (docs/model.md §3)
            "image_size": config.model.image_size,
            # the renders' estimator: coarse + importance samples a ray (a figure depends on it, docs/model.md §5)
            "samples": [config.render.eval_coarse, config.render.eval_fine],
            "subject": str(loaded.capture.root),
            "protocol": loaded.protocol.name,
            "poses": "corrected" if loaded.refined else "capture",
        }

    views = spread(loaded.protocol.split("train"), COVERAGE_VIEWS)
    coverage = training_coverage(loaded.capture, views, loaded.body_model.faces, r.progress)
    score = lambda split: _score_split(loaded, split, out_dir, r, coverage)  # noqa: E731
    return evaluate_splits(out_dir, r.splits, score, header, markdown_table)


def open_other_capture(run, run_dir: Path, root: Path) -> ZjuCapture:
    """Another recording of the run's person, read with the run's loader options: it must have ``splits.json`` (its
    excluded views are skipped) and, where both record one, the run's body model."""
    data = run.config.data
    other = ZjuCapture(root, data.ratio, data.mask_source, data.new_params, data.white_background)
    if not (other.root / "splits.json").is_file():
        raise CaptureError(f"{other.root}: no splits.json (prepare the recording with narf-prepare-capture)")
    record = capture_body_record(other)
    if record is not None and record["sha256"] != file_sha256(run.body_model.path):
        raise CaptureError(
            f"{other.root / 'body_model.json'}: its params belong to {record['file']} (sha256 {record['sha256'][:12]}"
            f"...), not to the body model of {run_dir} ({run.body_model.path})"
        )
    return other
