"""The person masks of a recording being prepared, as the silhouette term of its body fit
(``pipelines.body.silhouettes``; docs/guides/real-captures.md, "Body fit"): each raw mask limited to the body's
neighbourhood and without the other people around it, as the capture's final masks are
(``pipelines.prepare.people.occlusion.person_mask``), with the pixels of unknown owner beside them (the body may lie
there, behind somebody), undistorted and reduced."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pipelines.body.silhouettes import SilhouetteSettings, SilhouetteTerm, silhouette_targets
from pipelines.datasets.camera import Camera, silhouette
from pipelines.prepare.people.occlusion import person_mask


def reduced_mask(
    camera: Camera, raw: np.ndarray, vertices: np.ndarray, faces: np.ndarray, height: int, points, others=()
) -> tuple[np.ndarray, np.ndarray]:
    """The raw mask near the body with the other people cut out, and the pixels of unknown owner
    (``pipelines.prepare.people.occlusion.person_mask``; ``points`` the person's (T, 3) targets, ``others`` the other
    people's), both undistorted and reduced to ``height`` rows: (h, w) bool each."""
    scale = min(1.0, height / camera.height)
    small = camera.scaled(scale)
    size = (small.width, small.height)
    mask = cv2.resize(raw.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.5
    mask, unknown = person_mask(mask, silhouette(small, vertices, faces), small, points, list(others))
    if np.any(small.dist != 0):
        maps = cv2.initUndistortRectifyMap(small.K, small.dist, None, small.K, size, cv2.CV_32FC1)
        mask, unknown = (cv2.remap(m.astype(np.uint8), *maps, cv2.INTER_NEAREST) > 0 for m in (mask, unknown))
    return mask, unknown


def silhouette_stage(root, cameras: list[Camera], found, faces: np.ndarray, P: np.ndarray, settings=None):
    """The ``silhouettes`` argument of ``fit_body`` for a recording being prepared in ``root``: the raw masks
    (``root/.frames/mask_raw/<camera>/<source frame>.png``) of the views that agreed on the person, read for the
    frames asked for (indices into ``found.frames``) when the term is built."""
    settings = settings or SilhouetteSettings()

    def build(vertices: np.ndarray, frames: np.ndarray) -> SilhouetteTerm:
        masks, unknown = [], []
        for i, f in enumerate(frames):
            source, row = found.frames[f], []
            for v, camera in enumerate(cameras):
                if not found.used[f, v]:
                    row.append((None, None))
                    continue
                raw = cv2.imread(str(root / ".frames" / "mask_raw" / camera.name / f"{source:06d}.png"), 0) > 0
                others = found.others.get(source, [])
                row.append(reduced_mask(camera, raw, vertices[i], faces, settings.height, found.points[f], others))
            masks.append([m for m, _ in row])
            unknown.append([u for _, u in row])
        return SilhouetteTerm(silhouette_targets(cameras, masks, settings, unknown), P, settings)

    return build


def staged_person_mask(root: Path, camera, found, i: int, body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The person's mask and the pixels of unknown owner (``pipelines.prepare.people.occlusion.person_mask``) of frame
    ``i`` of ``found`` in ``camera``, from its raw mask staged in ``root/.frames/mask_raw`` and the fitted ``body``'s
    silhouette (H, W) bool."""
    source = found.frames[i]
    raw = cv2.imread(str(root / ".frames" / "mask_raw" / camera.name / f"{source:06d}.png"), cv2.IMREAD_GRAYSCALE)
    return person_mask(raw > 0, body, camera, found.points[i], found.others.get(source, []))
