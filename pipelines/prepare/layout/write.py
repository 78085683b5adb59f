"""Writing the prepared capture in the ZJU-MoCap layout (docs/formats.md §1), with its splits, overlays and report.

``<camera>/<i:06d>.jpg`` (i: 0-based index of the kept frames), ``mask/`` and ``mask_cihp/`` (binary: 1 on the
person), ``params/<i>.npy`` and ``vertices/<i>.npy`` (with pose blend shapes, in the calibration's world),
``annots.npy`` (cameras with their distortion ``D``: the loader undistorts), ``intri.yml`` / ``extri.yml``,
``splits.json``, ``floor.json``, ``keypoints3d.npy``, ``overlay/`` and ``report.json``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np

from fitting.files import write_image, write_npy
from pipelines.datasets.camera import project_distorted, silhouette
from pipelines.datasets.easymocap import write_easymocap_cameras
from pipelines.datasets.floor import camera_up, feet_against_floor, floor_from_feet, write_floor
from pipelines.datasets.keypoints import TARGET_NAMES
from pipelines.datasets.zju_mocap import BODY_SURFACE, SmplParams, write_annots, write_body_surface, write_params
from pipelines.prepare.body.masks import staged_person_mask
from pipelines.prepare.layout.checks import draw_overlay, flag_cameras, iou, reprojection_notice
from pipelines.prepare.people.multiview import projection_matrix, relative_errors

OVERLAY_HEIGHT = 480  # rows of each camera's tile in overlay.mp4


def write_sequence(root: Path, cameras, found, fitted, vertices: np.ndarray) -> None:
    """Frames renumbered 0..F-1 (images moved from ``.frames``), params, vertices, annots and camera files."""
    frames = root / ".frames"
    for i, source in enumerate(found.frames):
        for cam in cameras:
            (root / cam.name).mkdir(parents=True, exist_ok=True)
            (frames / cam.name / f"{source:06d}.jpg").replace(root / cam.name / f"{i:06d}.jpg")
        params = SmplParams(fitted.poses[i], fitted.rh[i], fitted.th[i], fitted.shapes)
        write_params(root / "params" / f"{i}.npy", params)
        (root / "vertices").mkdir(exist_ok=True)
        write_npy(root / "vertices" / f"{i}.npy", vertices[i].astype(np.float32))
    ims = [[f"{cam.name}/{i:06d}.jpg" for cam in cameras] for i in range(len(found.frames))]
    write_annots(root / "annots.npy", cameras, ims)
    write_easymocap_cameras(root, cameras)
    if fitted.displacement is not None:
        write_body_surface(root / BODY_SURFACE, fitted.displacement)
    write_npy(root / "keypoints3d.npy", found.points.astype(np.float32))


def splits(n_frames: int, names: list[str], holdout: str | None, novel_fraction: float, excluded) -> dict:
    """Training / novel-pose frames (the last ``novel_fraction``) and training / novel-view cameras."""
    n_novel = int(round(novel_fraction * n_frames)) if n_frames > 1 else 0
    n_train = n_frames - n_novel
    test_views = [names.index(holdout)] if holdout else []
    return {
        "train_frames": list(range(n_train)),
        "novel_frames": list(range(n_train, n_frames)),
        "train_views": [v for v in range(len(names)) if v not in test_views],
        "test_views": test_views,
        "excluded": sorted(excluded),
    }


def _check_pass(root: Path, seen, found, fitted, vertices, faces, ious: dict, progress=None):
    """Final masks (``pipelines.prepare.people.occlusion.person_mask``: the raw ones limited to the body's
    neighbourhood, less the other people; the pixels of unknown owner in ``mask_unknown/``), overlays and IoU (of the
    known pixels) per (frame, view), a frame at a time: fills ``ious`` (camera -> list) and yields each frame of
    overlay.mp4 (RGB), so that nothing is held for the whole recording."""
    cameras = seen.cameras
    for cam in cameras:
        ious.setdefault(cam.name, [])
        for folder in ("mask", "mask_cihp", "overlay"):
            (root / folder / cam.name).mkdir(parents=True, exist_ok=True)
    for i in range(len(found.frames)):
        tiles = []
        for v, cam in enumerate(cameras):
            body = silhouette(cam, vertices[i], faces)
            mask, unknown = staged_person_mask(root, cam, found, i, body)
            for folder in ("mask", "mask_cihp"):
                write_image(root / folder / cam.name / f"{i:06d}.png", mask.astype(np.uint8))
            if unknown.any():  # somebody in front of the person (docs/formats.md §1.5)
                (root / "mask_unknown" / cam.name).mkdir(parents=True, exist_ok=True)
                write_image(root / "mask_unknown" / cam.name / f"{i:06d}.png", unknown.astype(np.uint8))
            if found.used[i, v]:
                ious[cam.name].append(iou(body & ~unknown, mask))
            image = cv2.imread(str(root / cam.name / f"{i:06d}.jpg"))
            targets = project_distorted(cam, fitted.targets[i])
            overlay = draw_overlay(image, body, found.distorted[i, v], targets, bool(found.used[i, v]))
            write_image(root / "overlay" / cam.name / f"{i:06d}.jpg", overlay, (cv2.IMWRITE_JPEG_QUALITY, 85))
            width = int(round(overlay.shape[1] * OVERLAY_HEIGHT / overlay.shape[0])) // 2 * 2
            tiles.append(cv2.resize(overlay, (width, OVERLAY_HEIGHT), interpolation=cv2.INTER_AREA))
            if progress is not None:
                progress()
        yield np.concatenate(tiles, axis=1)[..., ::-1]


def _errors(cameras, found, fitted) -> tuple[np.ndarray, np.ndarray]:
    """(F, T, V) reprojection errors (fraction of the height; NaN elsewhere) of the triangulated targets and of the
    fitted body's targets, against the detections of the views that agreed on the person (a view showing somebody
    else is counted as disagreeing, not measured)."""
    P = np.stack([projection_matrix(c) for c in cameras])
    heights = np.array([c.height for c in cameras], np.float64)
    xy = found.detected[..., :2].transpose(0, 2, 1, 3)
    used = (found.detected[..., 2] * found.used[..., None]).transpose(0, 2, 1) > 0
    triangulated = np.where(used, relative_errors(P, found.points, xy, heights), np.nan)
    body = np.where(used, relative_errors(P, fitted.targets, xy, heights), np.nan)
    return triangulated, body


def _median(values) -> float:
    values = np.asarray(values, np.float64)
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else float("nan")


def _camera_report(seen, found, triangulated, body, ious) -> dict:
    """Per camera: size, notes, views used / without a person / disagreeing, reprojection errors, IoU and how far the
    body fit moved the camera."""
    per_camera = {}
    for v, cam in enumerate(seen.cameras):
        height = cam.height
        per_camera[cam.name] = {
            "size": [cam.width, cam.height],
            **seen.recordings.get(cam.name, {}),
            "notes": seen.notes.get(cam.name, []),
            "views_used": int(found.used[:, v].sum()),
            "views_without_person": found.view_notes[v]["no_person"],
            "views_showing_others": found.view_notes[v]["other_person"],
            "views_disagreeing": found.view_notes[v]["disagreed"],
            "views_overlapped_by_others": found.view_notes[v]["overlapped"],
            "triangulation_reprojection_px": _median(triangulated[..., v]) * height,
            "body_reprojection_px": _median(body[..., v]) * height,
            "body_reprojection_pct_height": 100 * _median(body[..., v]),
            "iou_mean": float(np.mean(ious[cam.name])) if ious[cam.name] else float("nan"),
            "iou_min": float(np.min(ious[cam.name])) if ious[cam.name] else float("nan"),
        }
        if cam.name in seen.corrections:  # how far the body fit moved the camera (docs/guides/real-captures.md)
            turn, shift = seen.corrections[cam.name]
            per_camera[cam.name]["calibration_correction"] = {"turn_degrees": turn, "shift_cm": shift}
        if cam.name in seen.depths:  # then moved along its axis (pipelines.prepare.body.camera_depth)
            per_camera[cam.name].setdefault("calibration_correction", {}).update(seen.depths[cam.name])
    return per_camera


def write_capture(root: Path, seen, found, fitted, vertices, faces, holdout, request, calibration) -> dict:
    """The layout stage of a prepare: the frames, bodies and cameras (:func:`write_sequence`), the floor (the
    request's, or found under the fitted feet) and the masks, overlays, splits and report (:func:`finish_capture`),
    all in ``root``; returns the report."""
    write_sequence(root, seen.cameras, found, fitted, vertices)
    floor = request.floor or floor_from_feet(vertices, camera_up(seen.cameras))
    write_floor(root, floor)
    return finish_capture(root, seen, found, fitted, vertices, faces, holdout, request, calibration, floor)


def finish_capture(root: Path, seen, found, fitted, vertices, faces, holdout, request, calibration, floor) -> dict:
    """Masks, overlays, splits and the report (returned, and written to ``report.json``)."""
    from tqdm import tqdm

    from fitting.video import write_mp4
    from pipelines.prepare.layout.colour import write_capture_colour

    cameras, names = seen.cameras, [c.name for c in seen.cameras]
    ious = {}
    total = len(found.frames) * len(cameras)
    with tqdm(total=total, desc="masks and overlays", unit="view", disable=not request.progress) as bar:
        write_mp4(
            root / "overlay" / "overlay.mp4",
            _check_pass(root, seen, found, fitted, vertices, faces, ious, bar.update),
            fps=15,
        )
    shutil.rmtree(root / ".frames")
    triangulated, body = _errors(cameras, found, fitted)
    excluded = [[i, v] for i in range(len(found.frames)) for v in range(len(cameras)) if not found.used[i, v]]
    split = splits(len(found.frames), names, holdout, request.novel_fraction, excluded)
    (root / "splits.json").write_text(json.dumps(split, indent=1))
    per_camera = _camera_report(seen, found, triangulated, body, ious)
    errors = {n: _median(body[..., v]) for v, n in enumerate(names)}
    disagreed = {n: found.view_notes[v]["disagreed"] / max(1, len(seen.frames[v])) for v, n in enumerate(names)}
    ious = {n: per_camera[n]["iou_mean"] for n in names}
    flags = flag_cameras(names, errors, ious, disagreed, seen.corrections)
    for name, reason in flags.items():
        per_camera[name]["flag"] = reason
    distance = np.linalg.norm(fitted.targets - found.points, axis=-1)
    report = {
        "recording": str(request.recording),
        "calibration": str(calibration),
        "cameras": per_camera,
        "flagged_cameras": flags,
        "frames": {
            "read": len(set().union(*map(set, seen.frames))),
            "common": len(set.intersection(*map(set, seen.frames))),
            "kept": len(found.frames),
            "source_frames": found.frames,
            "dropped": {str(k): v for k, v in found.dropped.items()},
        },
        "joints": {
            name: {
                "triangulation_pct_height": 100 * _median(triangulated[:, t]),
                "body_to_triangulated_cm": 100 * _median(distance[:, t]),
            }
            for t, name in enumerate(TARGET_NAMES)
        },
        "summary": {
            "median_reprojection_pct_height": 100 * _median(body),
            "median_triangulation_pct_height": 100 * _median(triangulated),
            "min_camera_iou": min((p["iou_mean"] for p in per_camera.values()), default=float("nan")),
            "body_to_triangulated_cm": 100 * _median(distance),
        }
        | _displacement(fitted),
        "splits": {k: v for k, v in split.items() if k != "excluded"} | {"excluded_views": len(excluded)},
        "floor": floor.to_json() | feet_against_floor(vertices, floor),
        "sync": seen.sync,
        "notices": _notices(seen, split) + [n for n in [reprojection_notice(errors)] if n],
    }
    if seen.detections:
        report["detections"] = seen.detections
    if seen.person:
        report["person"] = seen.person
    report["colour"] = write_capture_colour(root, progress=request.progress)
    (root / "report.json").write_text(json.dumps(_json_ready(report), indent=1, allow_nan=False))
    return report


def _displacement(fitted) -> dict:
    """The surface's displacement along the template's normals (SMPL+D; ``pipelines.prepare.body.fit``), cm."""
    if fitted.displacement is None:
        return {}
    size = 100 * np.abs(fitted.displacement)
    return {"surface_displacement_cm": {"median": float(np.median(size)), "p99": float(np.percentile(size, 99))}}


def _notices(seen, split: dict) -> list[str]:
    """What the capture left out or assumed that a user would not see otherwise: recordings without a calibrated
    camera, frames only some cameras have, videos of different frame rates, a capture too short for novel-pose
    frames."""
    notes = []
    if seen.unused_recordings:
        notes.append(f"recordings without a calibrated camera, left out: {', '.join(seen.unused_recordings)}")
    counts = {c.name: len(f) for c, f in zip(seen.cameras, seen.frames)}
    if len(set(counts.values())) > 1:
        shared = len(set.intersection(*map(set, seen.frames)))
        fewer = ", ".join(f"{n} {k}" for n, k in counts.items() if k < max(counts.values()))
        notes.append(
            f"cameras with fewer frames ({fewer} of {max(counts.values())}): the capture keeps the {shared} all share"
        )
    rates = {n: round(r, 2) for n, r in seen.frame_rates.items() if r}
    if len(set(rates.values())) > 1:
        listed = ", ".join(f"{n} {r:g}" for n, r in rates.items())
        notes.append(f"the videos' frame rates differ ({listed} fps): frames are paired by index, so check the sync")
    if not split["novel_frames"]:
        notes.append(
            f"{len(split['train_frames'])} frame(s) kept: no novel-pose frames (splits.json novel_frames is empty)"
        )
    return notes


def _json_ready(value):
    """NaN (a value with nothing to measure: a target the detector has no point for) as JSON null."""
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_ready(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
