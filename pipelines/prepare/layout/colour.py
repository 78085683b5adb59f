"""Each camera's colour gain, measured on the floor (docs/formats.md §1.12; docs/model.md §6, *Measured camera
colour*).

The cameras of a rig differ in white balance and exposure, and a fit that sees three of them learns their mean look,
which a fourth camera does not record. The floor around the person is static, (nearly) matte and seen by every
camera, so a point of it has one colour, and two cameras' pixels at its projections differ by the ratio of their
gains:

* each camera's **background** is the per-pixel median of a few frames with the person's (and unknown owners')
  pixels left out, so that the person and whoever walks by are gone;
* **floor points** lie on a grid of the floor plane (``floor.json``) around the bodies' positions, projected into
  each camera with its distortion;
* for each pair of cameras a and b and each channel, ``log g_a - log g_b`` is the median over the points both see of
  ``log I_a - log I_b`` (pixels near black or white left out); the log gains are the least-squares solution of those
  equations with their sum over the cameras 0.

A camera that shares fewer than ``min_points`` points with every other keeps the gain 1 and is reported unmeasured.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from pipelines.datasets.camera import project_distorted
from pipelines.datasets.camera_colour import GAIN_RANGE

#: colours (0-255) below or above which a channel is too dark or clipped to be compared
DARK, BRIGHT = 8, 247


def background_image(views, long_side: int = 640) -> tuple[np.ndarray, float]:
    """The static scene of one camera: the per-pixel median of ``views`` ((BGR uint8 image, bool person mask)
    pairs), downscaled so that its long side is at most ``long_side``; pixels that are the person's in more than
    two thirds of the views are NaN. Returns (h, w, 3) float32 BGR and the scale (background pixels per image
    pixel). Every view is dilated by 2 % of the image's long side, so that the person's blur and shadow edge go too."""
    images, free = [], []
    scale = 1.0
    for bgr, person in views:
        scale = min(1.0, long_side / max(bgr.shape[:2]))
        size = (round(bgr.shape[1] * scale), round(bgr.shape[0] * scale))
        grow = max(3, int(0.02 * max(bgr.shape[:2])) * 2 + 1)
        person = cv2.dilate(person.astype(np.uint8), np.ones((grow, grow), np.uint8))
        images.append(cv2.resize(bgr, size, interpolation=cv2.INTER_AREA).astype(np.float32))
        free.append(cv2.resize(person, size, interpolation=cv2.INTER_NEAREST) == 0)
    stack, free = np.stack(images), np.stack(free)
    stack[~free] = np.nan
    enough = free.sum(0) * 3 >= len(images)
    with warnings.catch_warnings():  # all-NaN pixels: NaN, as intended
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(stack, axis=0)
    median[~enough] = np.nan
    return median, scale


def floor_grid(up: np.ndarray, height: float, centres: np.ndarray, pad: float, spacing: float) -> np.ndarray:
    """(N, 3) points of the floor {x : x . up = height} on a square grid of ``spacing`` metres covering the
    ``centres``' (F, 3) feet on the floor, padded by ``pad`` metres."""
    up = up / np.linalg.norm(up)
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    plane = np.stack([centres @ e1, centres @ e2], axis=1)
    low, high = plane.min(0) - pad, plane.max(0) + pad
    u, v = (np.arange(low[i], high[i] + spacing / 2, spacing) for i in range(2))
    uu, vv = np.meshgrid(u, v, indexing="ij")
    return uu.reshape(-1, 1) * e1 + vv.reshape(-1, 1) * e2 + height * up


def floor_colours(backgrounds: list[np.ndarray], scales: list[float], cameras, points: np.ndarray) -> np.ndarray:
    """(C, N, 3) BGR colour of each floor point in each camera's background (nearest pixel), NaN where the camera
    does not see it (behind it, outside the image, an unknown background pixel, a channel too dark or clipped)."""
    out = np.full((len(cameras), len(points), 3), np.nan, np.float32)
    for c, (camera, background, scale) in enumerate(zip(cameras, backgrounds, scales)):
        depth = points @ camera.cam_from_world[2, :3] + camera.cam_from_world[2, 3]
        pixels = np.rint(project_distorted(camera, points) * scale).astype(np.int64)
        h, w = background.shape[:2]
        inside = (depth > 0.1) & (pixels[:, 0] >= 0) & (pixels[:, 0] < w) & (pixels[:, 1] >= 0) & (pixels[:, 1] < h)
        colour = background[pixels[inside, 1], pixels[inside, 0]]
        colour[((colour < DARK) | (colour > BRIGHT)).any(-1)] = np.nan
        out[c, inside] = colour
    return out


def solve_gains(colours: np.ndarray, min_points: int = 50) -> dict:
    """Gains (C, 3) RGB from floor colours (C, N, 3) BGR (module docstring), with each camera's ``points`` (the most
    it shares with another camera), ``residual`` (the median over its pairs of the pair equation's misfit, in log
    units: 0.01 is 1 %) and ``measured`` (False: it kept the gain 1).

    Only one group of cameras linked by pairs is measured, the largest: the gain between groups that share fewer
    than ``min_points`` points is not determined by the floor (the least-squares problem is rank-deficient), so the
    other groups keep the gain 1. A camera whose gain comes out of ``GAIN_RANGE`` (a fit refuses it) is not a
    white balance but a measurement gone wrong: it is left out and the rest solved again."""
    n = len(colours)
    logs = np.log(colours[..., ::-1])  # RGB
    pairs, targets, shared = [], [], np.zeros(n, int)
    for a in range(n):
        for b in range(a + 1, n):
            both = np.isfinite(logs[a]).all(-1) & np.isfinite(logs[b]).all(-1)
            shared[a], shared[b] = max(shared[a], both.sum()), max(shared[b], both.sum())
            if both.sum() >= min_points:
                pairs.append((a, b))
                targets.append(np.median(logs[a, both] - logs[b, both], axis=0))
    dropped = np.zeros(n, bool)
    while True:
        kept = [(pair, target) for pair, target in zip(pairs, targets) if not dropped[list(pair)].any()]
        linked = _largest_group(n, [pair for pair, _ in kept])
        kept = [(pair, target) for pair, target in kept if linked[pair[0]]]
        log_gains = np.zeros((n, 3))
        if kept:
            system = np.zeros((len(kept) + 1, n))
            for row, ((a, b), _) in enumerate(kept):
                system[row, a], system[row, b] = 1.0, -1.0
            system[-1] = linked  # the last row: the measured gains' logs sum to 0
            rhs = np.vstack([*(target for _, target in kept), np.zeros(3)])
            log_gains[linked] = np.linalg.lstsq(system[:, linked], rhs, rcond=None)[0]
        outside = linked & ((log_gains < np.log(GAIN_RANGE[0])) | (log_gains > np.log(GAIN_RANGE[1]))).any(-1)
        if not outside.any():
            break
        dropped[np.argmax(np.abs(log_gains).max(-1) * outside)] = True  # the farthest first, then solve again
    misfit = [[] for _ in range(n)]
    for (a, b), target in kept:
        error = float(np.abs(target - (log_gains[a] - log_gains[b])).max())
        misfit[a].append(error)
        misfit[b].append(error)
    residual = np.array([np.median(m) if m else np.nan for m in misfit])
    return {"method": "floor", "gains": np.exp(log_gains), "points": shared, "residual": residual, "measured": linked}


def _largest_group(n: int, pairs: list[tuple[int, int]]) -> np.ndarray:
    """(n,) bool: the cameras of the largest group that ``pairs`` link (none when there is no pair; ties: the group
    of the lowest camera)."""
    group = list(range(n))

    def root(c: int) -> int:
        while group[c] != c:
            c = group[c]
        return c

    for a, b in pairs:
        group[root(a)] = root(b)
    paired = {c for pair in pairs for c in pair}
    roots = [root(c) if c in paired else -1 for c in range(n)]
    sizes = {r: roots.count(r) for r in set(roots) if r >= 0}
    if not sizes:
        return np.zeros(n, bool)
    best = max(sizes, key=lambda r: (sizes[r], -roots.index(r)))
    return np.array([r == best for r in roots])


def measure_camera_colour(capture, frames: list[int], pad: float = 1.0, spacing: float = 0.04, progress=False) -> dict:
    """Each camera's gain in ``capture`` (a ``ZjuCapture`` with a floor) from the backgrounds of ``frames``
    (:func:`solve_gains`'s result). Raises ValueError when the capture has no ``floor.json``."""
    floor = capture.floor
    if floor is None:
        raise ValueError(f"{capture.root}: no floor.json, so no floor to compare the cameras on")
    centres = np.stack([capture.vertices(f).mean(0) for f in frames])
    points = floor_grid(np.asarray(floor.up, float), floor.height, centres, pad, spacing)
    backgrounds, scales = [], []
    bar = tqdm(total=len(frames) * capture.n_cameras, desc="camera colour", unit="view", disable=not progress)
    for cam in range(capture.n_cameras):

        def views(cam=cam):
            for frame in frames:
                yield capture.person_pixels(frame, cam)
                bar.update()

        background, scale = background_image(views())
        backgrounds.append(background)
        scales.append(scale)
    bar.close()
    return solve_gains(floor_colours(backgrounds, scales, capture.cameras, points))


def write_capture_colour(root, n_frames: int = 20, progress: bool = False) -> dict:
    """Measure the gains of the capture at ``root`` (its masks: ``mask/``, ``mask_cihp/`` or both, and
    ``floor.json``) on ``n_frames`` frames spread over the take, write ``colour.json`` and return the report's
    ``colour`` entry."""
    from pipelines.datasets.camera_colour import write_camera_colour
    from pipelines.datasets.capture import ZjuCapture

    root = Path(root)
    sources = [source for source, folder in (("mask", "mask"), ("cihp", "mask_cihp")) if (root / folder).is_dir()]
    source = "union" if len(sources) == 2 else sources[0] if sources else "mask"  # none: the reader names the file
    capture = ZjuCapture(root, ratio=1.0, mask_source=source)
    frames = sorted({round(i) for i in np.linspace(0, capture.n_frames - 1, min(n_frames, capture.n_frames))})
    measured = measure_camera_colour(capture, frames, progress=progress)
    names = [c.name for c in capture.cameras]
    write_camera_colour(root / "colour.json", names, measured)
    return {
        "method": measured["method"],
        "cameras": {
            name: {
                "gain": [float(v) for v in measured["gains"][i]],
                "floor_points": int(measured["points"][i]),
                "measured": bool(measured["measured"][i]),
            }
            for i, name in enumerate(names)
        },
    }


def colour_summary(colour: dict) -> str:
    """The report's ``colour`` entry as one line: each camera's R/G/B gains."""
    parts = []
    for name, entry in colour["cameras"].items():
        gain = "/".join(f"{v:.3f}" for v in entry["gain"]) if entry["measured"] else "not measured (gain 1)"
        parts.append(f"{name} {gain}")
    return f"R/G/B gains measured on the {colour['method']}: " + ", ".join(parts)
