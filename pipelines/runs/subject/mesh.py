"""Meshes out of a fitted run (``narf-export-mesh``) and their accuracy against true surfaces (``narf-eval --mesh``).

Meshes are in the capture's world (metres), with vertex colours and a per-vertex part index (the NARF part order
of ``narf.kinematics.PART_JOINTS``): a ``part`` vertex property in PLY, a ``_PART`` vertex attribute in glTF
binary, and a ``<stem>_parts.txt`` file beside an OBJ (which has no place for it). See docs/design.md *Meshes out*.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh

from fitting.files import atomic_write_bytes
from fitting.fitted import SavedRun, run_folder
from fitting.mesh import ExtractedMesh, extract_mesh, surface_metrics
from fitting.mesh_level import LevelChoice, LevelView, choose_level
from narf.fields import model_spec
from pipelines.body.model import pose_batch
from pipelines.datasets.errors import CaptureError
from pipelines.runs.requests import EvalRequest, ExportRequest, MotionClip
from pipelines.runs.subject.session import LoadedRun, box_frames, load_run, poses_for_frames
from pipelines.runs.subject.video import motion_params

MESH_SUFFIXES = (".ply", ".obj", ".glb")


def to_trimesh(mesh: ExtractedMesh) -> trimesh.Trimesh:
    out = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    rgba = np.concatenate([mesh.colours, np.ones((len(mesh.colours), 1))], axis=1)
    out.visual.vertex_colors = (rgba * 255 + 0.5).astype(np.uint8)
    return out


def write_mesh(path: Path, mesh: ExtractedMesh) -> list[Path]:
    """Write a mesh (format from the suffix) atomically; returns the files written."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"{path}: unknown mesh format '{suffix}'; use {', '.join(MESH_SUFFIXES)}")
    out = to_trimesh(mesh)
    written = [path]
    if suffix == ".ply":
        out.vertex_attributes["part"] = mesh.parts.astype(np.uint8)
        data = out.export(file_type="ply", include_attributes=True)
    elif suffix == ".glb":
        out.vertex_attributes["_PART"] = mesh.parts.astype(np.float32)  # glTF custom attributes are float
        data = out.export(file_type="glb")
    else:
        data = out.export(file_type="obj", include_color=True).encode()
        sidecar = path.with_name(f"{path.stem}_parts.txt")
        atomic_write_bytes(sidecar, ("\n".join(str(int(p)) for p in mesh.parts) + "\n").encode())
        written.append(sidecar)
    atomic_write_bytes(path, data)
    return written[::-1]


def _capture_pose(run: LoadedRun, frame: int, device: str):
    pose, _, _ = poses_for_frames(run, run.body_model, [frame])
    return run.colour_poses(pose, [frame]).to(device)  # the vertex colours' pose features (docs/model.md §4)


def fit_level(run: LoadedRun, device: str, n_frames: int = 4, n_cameras: int = 4) -> LevelChoice:
    """The mesh level of a run chosen from its own training views (``fitting.mesh_level``): ``n_frames`` evenly
    spaced training frames, each seen by up to ``n_cameras`` evenly spaced training cameras."""
    protocol = run.protocol
    cameras = box_frames(list(protocol.train_views), n_cameras)
    frames = []
    for frame in box_frames(list(protocol.train_frames), n_frames):
        views = []
        for _, cam in protocol.usable([frame], cameras):
            item = run.capture.load_frame(frame, cam)
            views.append(LevelView(item.camera.K, item.camera.cam_from_world, item.mask > 0.5, item.band))
        if views:
            frames.append((_capture_pose(run, frame, device), views))
    return choose_level(run.field, frames)


def resolve_level(run: LoadedRun, level: float | None, device: str) -> tuple[float, dict]:
    """``level`` when given, else the fit's own (:func:`fit_level`, chosen once per loaded run: every split of an
    evaluation uses it); with a record for reports."""
    if level is not None:
        return level, {"level": level, "level_source": "given"}
    if run.mesh_level is None:
        choice = fit_level(run, device)
        record = {"level": choice.level, "level_source": "training masks", "level_iou": choice.iou}
        run.mesh_level = record | {"level_views": choice.n_views}
    return run.mesh_level["level"], dict(run.mesh_level)


def export_run_meshes(run: Path | SavedRun, request: ExportRequest) -> tuple[list[Path], dict]:
    """Export the fitted body at a capture frame, or at frames ``window = (A, B)`` (B excluded) of a motion file
    placed on the capture's stage as for videos (one file per frame: ``<stem>_<frame>.<ext>``). ``level`` None:
    chosen from the fit (:func:`resolve_level`). Returns the files written and the level's record."""
    r = request
    out, frame, motion, device, progress = Path(r.out), r.frame, r.motion, r.device, r.progress
    if out.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{out}: unknown mesh format '{out.suffix}'; use {', '.join(MESH_SUFFIXES)}")
    run_dir = run_folder(run)
    run = load_run(run, device)
    if not model_spec(run.config.model.name).meshes:
        raise ValueError(f"{run_dir}: the CNN baseline renders images, not a density field: no mesh to export")
    if motion is None and (frame is None or not 0 <= frame < run.capture.n_frames):
        raise CaptureError(f"{run.capture.root}: frame {frame} out of range (0..{run.capture.n_frames - 1})")
    if motion is not None:
        start, stop = r.window or (0, None)
        clip = MotionClip(Path(motion), start, None if stop is None else stop - start, flag="--frames")
        params, _ = motion_params(run, clip)
    level, record = resolve_level(run, r.level, device)
    resolution = r.resolution
    if motion is None:
        mesh = extract_mesh(run.field, _capture_pose(run, frame, device), resolution, level, progress=progress)
        return write_mesh(out, mesh), record
    written = []
    for k, p in enumerate(params):
        with torch.no_grad():
            body = run.body_model.pose_zju(*(torch.as_tensor(v)[None] for v in (p.poses, p.rh, p.th, p.shapes)))
        pose = run.colour_poses(pose_batch(body))  # a new motion's colour (docs/model.md §4)
        mesh = extract_mesh(run.field, pose.to(device), resolution, level, progress=progress)
        written += write_mesh(out.with_name(f"{out.stem}_{start + k:05d}{out.suffix}"), mesh)
    return written, record


def true_surface(root: Path, frame: int) -> trimesh.Trimesh | None:
    """The capture's true surface of a frame (``surfaces/<frame>.ply``, written by the synthetic generator)."""
    path = Path(root) / "surfaces" / f"{frame}.ply"
    if not path.is_file():
        return None
    try:
        return trimesh.load(path, file_type="ply", process=False, force="mesh")
    except (ValueError, OSError, KeyError) as err:
        raise CaptureError(f"{path}: unreadable PLY mesh ({err})") from err


def mesh_accuracy(run: LoadedRun, frames: list[int], out_dir: Path, request: EvalRequest) -> dict:
    """Surface distance and normal consistency of the exported mesh against the true surface, per frame and
    averaged, over the ``frames`` that have a true surface; the meshes go to ``out_dir/<frame>.ply``, extracted at
    ``request.mesh_resolution`` and ``request.mesh_level`` (None: chosen from the fit, :func:`resolve_level`, as
    narf-export-mesh does)."""
    resolution, device, progress = request.mesh_resolution, request.device, request.progress
    truths = {f: true_surface(run.capture.root, f) for f in frames}
    frames = [f for f in frames if truths[f] is not None]
    if not frames:
        raise CaptureError(
            f"{run.capture.root}: no true surfaces (surfaces/<frame>.ply) for the split's frames; --mesh needs a "
            "capture that ships them, as the synthetic captures do"
        )
    level, level_record = resolve_level(run, request.mesh_level, device)
    records = []
    for frame in frames:
        mesh = extract_mesh(run.field, _capture_pose(run, frame, device), resolution, level, progress=progress)
        write_mesh(Path(out_dir) / f"{frame}.ply", mesh)
        records.append({"frame": frame, **surface_metrics(to_trimesh(mesh), truths[frame])})
    keys = ("mean_mm", "p95_mm", "normal_consistency")
    return {
        "frames": frames,
        "resolution": resolution,
        **level_record,
        **{k: float(np.mean([r[k] for r in records])) for k in keys},
        "per_frame": records,
    }
