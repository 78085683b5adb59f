"""Evaluate a fitted run on its capture's protocol splits (``narf-eval``)."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from tqdm import tqdm

from fitting.evaluate import (
    average_metrics,
    frame_metrics,
    library_versions,
    markdown_table,
    nb_crop_region,
    render_view,
    spread,
    write_report,
)
from fitting.plots import grid, save_png, to_numpy
from pipelines.body.locate import file_sha256
from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.zju_mocap import CaptureError
from pipelines.runs.requests import EvalRequest, refuse_options
from pipelines.runs.subject.session import capture_body_record, load_run, poses_for_frames


def _view_metrics(run, split: str, items, frames: list[int], out_dir: Path, grids: int, device: str, progress: bool):
    """Render every (frame, camera) of ``items`` and score it against the capture (full image and NB crop); the
    first ``grids`` views also go to ``out_dir/grids/<split>/``. Returns one record per view. The run's own capture
    is posed as the run shows it (corrected training frames); another capture (``run.other``) with its own poses."""
    config, field = run.config, run.field
    capture = run.capture if split != "capture" else run.other
    poses, _, _ = poses_for_frames(run if split != "capture" else capture, run.body_model, frames)
    poses = poses.to(device)
    bg = 1.0 if config.data.white_background else 0.0
    records = []
    for index, (frame, cam) in enumerate(tqdm(items, desc=f"eval {split}", unit="view", disable=not progress)):
        item = capture.load_frame(frame, cam)
        pose = poses.select(torch.tensor([frames.index(frame)], device=device))
        render = to_numpy(render_view(field, item.camera, pose, config))
        region = nb_crop_region(item.camera, capture.vertices(frame))
        records.append(
            {"frame": frame, "camera": cam, **frame_metrics(render, item.image, item.mask, region, bg, item.band)}
        )
        if index < grids:
            save_png(out_dir / "grids" / split / f"frame{frame:05d}_cam{cam:02d}.png", grid(item.image, render))
    return records


def evaluate_run(
    run_dir: Path,
    splits: list[str],
    limit: int | None = None,
    device: str = "cpu",
    progress: bool = True,
    grids: int = 4,
    mesh: bool = False,
    mesh_resolution: int = 256,
    mesh_level: float | None = None,
    other: Path | None = None,
) -> dict:
    """Evaluate ``splits`` of the run's protocol; update ``run_dir/eval/metrics.json`` and ``metrics.md``.

    With ``mesh``, also the surface of each split frame that has a true surface (``surfaces/<frame>.ply``):
    ``pipelines.runs.subject.mesh.mesh_accuracy``, meshes in ``eval/meshes/<split>/``. ``other``: another prepared
    capture of the same person, evaluated as split ``capture`` (:func:`open_other_capture`).
    """
    run_dir = Path(run_dir)
    run = load_run(run_dir, device)
    config, capture, protocol = run.config, run.capture, run.protocol
    if other is not None:
        run.other = open_other_capture(run, run_dir, Path(other))
    out_dir = run_dir / "eval"
    metrics_path = out_dir / "metrics.json"
    report = json.loads(metrics_path.read_text()) if metrics_path.is_file() else {"splits": {}}
    for split in splits:
        if split == "capture":
            every = run.other.protocol()
            items = spread(every.usable(range(run.other.n_frames), range(run.other.n_cameras)), limit)
        else:
            items = spread(protocol.split(split), limit)
        if not items:
            raise ValueError(f"split '{split}' is empty for {capture.root} under the {protocol.name} protocol")
        frames = sorted({f for f, _ in items})
        records = _view_metrics(run, split, items, frames, out_dir, grids, device, progress)
        report["splits"][split] = {
            "n_views": len(records),
            "limit": limit,
            "full": average_metrics(records, "full"),
            "nb_crop": average_metrics(records, "nb_crop"),
            "per_view": records,
            **({"capture": str(run.other.root)} if split == "capture" else {}),
        }
        if mesh:
            from pipelines.runs.subject.mesh import mesh_accuracy

            report["splits"][split]["mesh"] = mesh_accuracy(
                run, frames, out_dir / "meshes" / split, mesh_resolution, mesh_level, device, progress
            )
    report.update(
        {
            "run": str(run_dir),
            "step": run.step,
            "model": config.model.name,
            "width": config.model.width,
            "image_size": config.model.image_size,
            "subject": str(capture.root),
            "protocol": protocol.name,
            "poses": "corrected" if run.refined else "capture",
            "versions": library_versions(),
        }
    )
    write_report(out_dir, report, markdown_table(report))
    return report


def evaluate(run_dir: Path, request: EvalRequest) -> dict:
    """``evaluate_run`` for a request (the kind table's entry point)."""
    users = "autoencoder runs"
    refuse_options(run_dir, "subject", {"--surreal": request.surreal, "--refine-steps": request.refine_steps}, users)
    r = request
    if r.capture is not None and tuple(r.splits) != ("capture",):
        raise ValueError("--capture evaluates every frame and camera of the other recording as the split 'capture'")
    return evaluate_run(
        run_dir,
        list(r.splits),
        r.limit,
        r.device,
        r.progress,
        r.grids,
        r.mesh,
        r.mesh_resolution,
        r.mesh_level,
        r.capture,
    )


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
