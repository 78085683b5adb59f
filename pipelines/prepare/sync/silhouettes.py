"""Cameras in step, a second look from the silhouettes (docs/guides/real-captures.md, *Cameras in step*).

The keypoint estimate (:mod:`pipelines.prepare.sync.keypoints`) reads an offset from where a detector puts each joint. A
detector whose error in one view follows the motion (a swinging limb blurred or half hidden from that side) leaves the
same mark there as a time offset. The masks give an estimate that does not go through the joints' places: for camera
c and frame t, the cells of a grid around the person (the box of the joints triangulated at t, padded by ``PAD``
metres, ``GRID`` cells a side) that project inside every other camera's mask at t are their visual hull; the share of
those cells that project inside c's own mask at frame t - d (the frame that shows the others' instant t if c is d
frames late), over the frames, scores the offset d (d, its sign and the whole-frame shifts as in
:mod:`pipelines.prepare.sync.keypoints`: a camera started k frames late has d = +k).

A calibration error moves c's projection of the hull by about the same image distance in every frame, and lowers the
share at the offsets that move the mask the same way less than at the others: so at each d the share is taken with
the image translation of c's mask (within ``TRANSLATION_REACH`` pixels) that raises it most, the silhouettes' static
part, as each joint's median residual is the keypoints'.

The search starts from the keypoints' whole shifts and looks ``REACH`` frames either way. A camera out of step cuts
the others' hulls too, so whole-frame shifts are made one at a time: the camera whose best d raises its share most
over d = 0 (by at least ``MIN_GAIN`` of the share that d = 0 misses) is shifted, and every camera is scored again.
What is left below a frame is the vertex of the parabola through the best d and its two neighbours; ``curvature`` is
the share lost one frame either way there (a person standing still gives none, and an offset cannot be seen).

Masks are read at ``MASK_SIDE`` pixels along their longest side and kept packed (8 pixels a byte); at most
``FRAMES`` frames spread over the take are scored.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pipelines.datasets.camera import project_distorted

#: cells a side of the grid around the person
GRID = 40
#: metres added around the box of the triangulated joints (hands, feet and hair reach past them)
PAD = 0.25
#: longest side, in pixels, at which the masks are read
MASK_SIDE = 480
#: at most this many frames, spread over the take, are scored
FRAMES = 24
#: a whole shift is made when it removes this share of what the hull misses in step
MIN_GAIN = 0.05
#: a frame whose hull has fewer cells is not scored (the masks or the joints missed the person)
MIN_CELLS = 200
#: joints that must be triangulated for a frame's box
MIN_JOINTS = 4
#: a camera scored on fewer frames (a short take: each frame must be seen at every d) gets no estimate
MIN_FRAMES = 8
#: frames searched either way of the keypoints' whole shift
REACH = 3
#: the static part: image translations up to this many pixels (at ``MASK_SIDE``) each way, on a grid of this step
TRANSLATION_REACH, TRANSLATION_STEP = 8, 2


@dataclass
class _Masks:
    """Packed masks read on first use: ``folder/<camera>/<frame:06d>.png`` at ``MASK_SIDE``; None where a mask is
    missing or empty (not seen)."""

    folder: Path
    names: list[str]
    scale: list[float]
    cache: dict = field(default_factory=dict)

    def get(self, v: int, frame: int):
        key = (v, frame)
        if key not in self.cache:
            path = self.folder / self.names[v] / f"{frame:06d}.png"
            raw = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
            if raw is None or not raw.any():
                self.cache[key] = None
            else:
                size = (round(raw.shape[1] * self.scale[v]), round(raw.shape[0] * self.scale[v]))
                small = cv2.resize(raw, size, interpolation=cv2.INTER_AREA) > 0 if self.scale[v] < 1 else raw > 0
                self.cache[key] = (np.packbits(small.reshape(-1)), small.shape)
        return self.cache[key]


def inside(packed, pixels: np.ndarray) -> np.ndarray:
    """(N,) bool: whether each of ``pixels`` (N, 2; x, y at the packed mask's size, pixel centres at whole numbers as
    in OpenCV) falls on the mask (``packed``: (bits, (height, width)) as :class:`_Masks` keeps it); False off the
    image."""
    bits, (height, width) = packed
    xy = np.floor(pixels + 0.5).astype(np.int64)
    ok = (xy[:, 0] >= 0) & (xy[:, 1] >= 0) & (xy[:, 0] < width) & (xy[:, 1] < height)
    index = xy[ok, 1] * width + xy[ok, 0]
    out = np.zeros(len(pixels), bool)
    out[ok] = (bits[index >> 3] >> (7 - (index & 7))) & 1 == 1
    return out


def person_boxes(points: np.ndarray) -> np.ndarray:
    """(N, 2, 3) each frame's box (lowest, highest corner) of the triangulated joints ``points`` (N frames, T joints,
    3; NaN where not triangulated), padded by ``PAD``; NaN where under ``MIN_JOINTS`` joints are known."""
    known = np.isfinite(points).all(-1)  # (N, T)
    with warnings.catch_warnings():  # a frame with no joint gives an all-NaN min
        warnings.simplefilter("ignore", RuntimeWarning)
        boxes = np.stack([np.nanmin(points, axis=1) - PAD, np.nanmax(points, axis=1) + PAD], axis=1)
    boxes[known.sum(1) < MIN_JOINTS] = np.nan
    return boxes


def _on_mask(camera, points: np.ndarray, scale: float) -> np.ndarray:
    """(N, 2) where ``points`` (N, 3) fall in ``camera``'s mask read at ``scale`` of its size (pixel centres at whole
    numbers at both sizes: x' = (x + 1/2) scale - 1/2)."""
    return (project_distorted(camera, points) + 0.5) * scale - 0.5


def _cells(box: np.ndarray) -> np.ndarray:
    """(GRID^3, 3) the centres of the grid's cells in ``box`` (2, 3)."""
    steps = (np.arange(GRID) + 0.5) / GRID
    axes = [box[0, i] + steps * (box[1, i] - box[0, i]) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _translations() -> np.ndarray:
    """(K, 2) the image translations tried for a camera's static part: every ``TRANSLATION_STEP`` pixels (at
    ``MASK_SIDE``) within ``TRANSLATION_REACH`` along each axis."""
    steps = np.arange(-TRANSLATION_REACH, TRANSLATION_REACH + 1, TRANSLATION_STEP, dtype=float)
    return np.stack(np.meshgrid(steps, steps, indexing="ij"), axis=-1).reshape(-1, 2)


def shares(cameras, masks: _Masks, timeline, boxes, shifts, v: int, offsets, stride: int = 1) -> tuple[np.ndarray, int]:
    """((D,) mean share for each d of ``offsets`` (D,), frames scored) of camera v against the others' hulls, at each
    d with the image translation (the static part, module docstring) that raises it most; camera u's frame t is its
    source frame t - ``shifts[u]`` ``stride`` (the whole shifts made so far, in steps of the timeline, which reads
    every ``stride``-th frame: d and the shifts count steps, ``timeline`` holds frame numbers). A frame is scored at
    every d or not at all (every d is judged on the same frames); NaN everywhere when none is."""
    others = [u for u in range(len(cameras)) if u != v]
    moves = _translations()
    total, scored = np.zeros((len(offsets), len(moves))), 0
    chosen = np.unique(np.linspace(0, len(timeline) - 1, min(FRAMES, len(timeline))).round().astype(int))
    for n in chosen:
        own = [masks.get(v, timeline[n] - (d + shifts[v]) * stride) for d in offsets]
        if not np.isfinite(boxes[n]).all() or any(m is None for m in own):
            continue
        hull = _cells(boxes[n])
        for u in others:
            packed = masks.get(u, timeline[n] - shifts[u] * stride)
            hull = hull[:0] if packed is None else hull[inside(packed, _on_mask(cameras[u], hull, masks.scale[u]))]
            if len(hull) < MIN_CELLS:
                break
        if len(hull) < MIN_CELLS:
            continue
        pixels = _on_mask(cameras[v], hull, masks.scale[v])
        total += [[inside(m, pixels + move).mean() for move in moves] for m in own]
        scored += 1
    return (total.max(axis=1) / scored if scored else np.full(len(offsets), np.nan)), scored


def _vertex(curve: np.ndarray, best: int) -> tuple[float, float]:
    """(the parabola's vertex through ``curve`` at best - 1, best, best + 1, in [-0.5, 0.5] of best; the share lost
    one frame either way, their mean) for the index ``best``; (0, 0) at an end."""
    if best == 0 or best == len(curve) - 1:
        return 0.0, 0.0
    low, mid, high = curve[best - 1], curve[best], curve[best + 1]
    bend = low - 2 * mid + high
    vertex = 0.0 if bend >= 0 else float(np.clip(0.5 * (low - high) / bend, -0.5, 0.5))
    return vertex, float(mid - (low + high) / 2)


def silhouette_offsets(
    cameras, timeline: list[int], folder: Path, points: np.ndarray, start: list[int], stride: int = 1
) -> dict:
    """Every camera's offset from the silhouettes (module docstring), searched within ``REACH`` frames of ``start``
    (each camera's whole shift by the keypoints, by camera in order): by camera name, ``offset_frames`` (the whole
    shift made plus the parabola's vertex about the best d), ``whole_frames`` (the shifts made), ``curvature`` (share
    lost one frame either way of the best) and ``frames`` scored; {} for a camera scored on fewer than
    ``MIN_FRAMES`` frames.
    ``folder``: ``<camera>/<frame:06d>.png`` masks named by source frame; ``timeline``: the frames read (sorted);
    ``points`` (N frames, T joints, 3): the joints triangulated from every camera, for the boxes; ``stride``: the
    timeline's step in frames (the prepare's ``--stride``), the unit of ``start`` and of every offset returned."""
    names = [c.name for c in cameras]
    masks = _Masks(folder, names, [min(1.0, MASK_SIDE / max(c.width, c.height)) for c in cameras])
    boxes, shifts, offsets = person_boxes(points), list(start), np.arange(-REACH, REACH + 1)

    def score_all():
        return [shares(cameras, masks, timeline, boxes, shifts, v, offsets, stride) for v in range(len(cameras))]

    curves = score_all()
    for _ in range(len(cameras)):
        gains = []
        for v, (curve, scored) in enumerate(curves):
            if scored >= MIN_FRAMES and offsets[np.argmax(curve)]:
                best, here = curve.max(), curve[REACH]
                if best - here >= MIN_GAIN * (1 - here):
                    gains.append((best - here, v, int(offsets[np.argmax(curve)])))
        if not gains:
            break
        _, v, d = max(gains)
        shifts[v] += d
        curves = score_all()
    out = {}
    for v, (curve, scored) in enumerate(curves):
        if scored < MIN_FRAMES:
            out[names[v]] = {}
            continue
        best = int(np.argmax(curve))
        vertex, curvature = _vertex(curve, best)
        out[names[v]] = {
            "offset_frames": round(float(shifts[v] + offsets[best] + vertex), 2),
            "whole_frames": shifts[v],
            "curvature": round(curvature, 5),
            "frames": scored,
        }
    return out
