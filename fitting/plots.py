"""Images written by fitting and evaluation: training curve, validation renders, comparison grids."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import torch

from fitting.config import with_eval_samples
from fitting.files import atomic_output, write_image

_PALETTE = np.array([[(i * 67) % 256, (i * 151 + 80) % 256, (i * 211 + 40) % 256] for i in range(32)]) / 255.0


def colour_depth(depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) expected depth -> (H, W, 3) in [0, 1], near = bright, background black."""
    valid = mask > 0.5
    out = np.zeros((*depth.shape, 3))
    if valid.any():
        low, high = np.percentile(depth[valid], [1, 99])
        norm = 1 - np.clip((depth - low) / max(high - low, 1e-6), 0, 1)
        coloured = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1] / 255.0
        out[valid] = coloured[valid]
    return out


def colour_segmentation(labels: np.ndarray) -> np.ndarray:
    """(H, W) part index (-1 background) -> (H, W, 3)."""
    out = _PALETTE[np.clip(labels, 0, None) % len(_PALETTE)]
    out[labels < 0] = 0
    return out


def save_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    bgr = cv2.cvtColor((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR)
    with atomic_output(path) as tmp:
        write_image(tmp, bgr)


def grid(gt: np.ndarray, render: dict, labels: bool = True) -> np.ndarray:
    """ground truth | render | depth | part segmentation | error map (x4), one row."""
    rgb = render["rgb"]
    tiles = [gt, rgb, colour_depth(render["depth"], render["mask"])]
    if labels and "segmentation" in render:
        tiles.append(colour_segmentation(render["segmentation"]))
    error = np.clip(np.abs(rgb - gt).mean(-1) * 4, 0, 1)
    tiles.append(cv2.applyColorMap((error * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)[..., ::-1] / 255.0)
    return np.concatenate(tiles, axis=1)


def to_numpy(render: dict) -> dict:
    """Render tensors to numpy (float32, long labels kept)."""
    return {
        k: (v.cpu().numpy() if v.dtype == torch.long else v.detach().float().cpu().numpy()) for k, v in render.items()
    }


def write_validation(field, config, image: np.ndarray, camera, pose, path: Path, latent=None) -> Path:
    """Render ``camera`` / ``pose`` (and an autoencoder ``latent``) at the fit's validation samples
    (``RenderConfig.validation_samples``) and save ground truth | render | depth | ... ."""
    from fitting.evaluate import render_view

    preview = with_eval_samples(config, *config.render.validation_samples())
    save_png(path, grid(image, to_numpy(render_view(field, camera, pose, preview, latent))))
    return path


def write_curve(log_path: Path, out: Path, size: tuple[int, int] = (720, 360)) -> None:
    """Training PSNR against step, drawn with OpenCV (no plotting dependency)."""
    if not Path(log_path).is_file():
        return
    rows = [json.loads(line) for line in Path(log_path).read_text().splitlines() if line.strip()]
    rows = [r for r in rows if np.isfinite(r.get("psnr", np.nan))]
    if len(rows) < 2:
        return
    width, height = size
    canvas = np.full((height, width, 3), 255, np.uint8)
    steps = np.array([r["step"] for r in rows], float)
    values = np.array([r["psnr"] for r in rows], float)
    low, high = np.floor(values.min()), np.ceil(values.max()) + 1e-6
    margin = 50
    xs = margin + (steps - steps.min()) / max(steps.max() - steps.min(), 1) * (width - 2 * margin)
    ys = height - margin - (values - low) / (high - low) * (height - 2 * margin)
    cv2.rectangle(canvas, (margin, margin), (width - margin, height - margin), (180, 180, 180), 1)
    cv2.polylines(canvas, [np.stack([xs, ys], 1).astype(np.int32)], False, (200, 80, 20), 2, cv2.LINE_AA)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(canvas, "training PSNR (dB) vs step", (margin, 30), font, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    for value, y in ((low, height - margin), (high, margin)):
        cv2.putText(canvas, f"{value:.0f}", (5, int(y) + 5), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for step, x in ((steps.min(), margin), (steps.max(), width - margin)):
        cv2.putText(canvas, f"{step:.0f}", (int(x) - 15, height - 25), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    with atomic_output(out) as tmp:
        write_image(tmp, canvas)
