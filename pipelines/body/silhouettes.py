"""The person masks as a term of a body fit (docs/guides/real-captures.md, "Body fit"; docs/guides/fitting.md, *Bodies
refined against the masks*): two robust chamfer distances between the projected body and each view's mask.

* Outside: every projected vertex should lie on the mask: ``E_out = mean rho(D(pi(v)) / s)`` with D the distance
  transform of the mask's complement (distance to the nearest mask pixel), sampled bilinearly.
* Inside: every point of the mask's outline should have a projected vertex near it:
  ``E_in = mean rho(|b - pi(v_nn(b))| / s)``, v_nn the vertex whose projection is nearest to b (found again every
  few iterations, without gradient).

rho is Geman-McClure, ``r^2 / (r^2 + 1)``, and s a fraction of the image height: a mask that misses an arm or takes in
a chair costs a bounded amount, so the other terms (keypoints, a prior) keep the body where the mask is wrong. Both
terms work in undistorted pixels, on masks undistorted and reduced to at most ``height`` rows. Used by
``narf-prepare-capture``'s body fit (``pipelines.prepare.body.masks``) and by a subject fit's refinement of the
capture's bodies (``pipelines.runs.subject.body_refine``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class SilhouetteSettings:
    """The silhouette term's settings (module docstring); its weight and iterations are the body fit's
    (``pipelines.prepare.body.fit.FitSettings``)."""

    scale: float = 0.02  # fraction of the image height at which a residual counts half
    height: int = 256  # rows of the reduced masks
    outline_points: int = 200  # points of each mask's outline
    vertex_stride: int = 2  # every n-th vertex of the body enters the terms
    nearest_every: int = 10  # iterations between searches of the nearest vertices


@dataclass
class SilhouetteTargets:
    """Per frame f and view v: ``distance`` (F, V, h, w) the reduced masks' distance transforms (fraction of the
    reduced height; 1 beyond a smaller view's reduced size); ``outline`` (F, V, B, 2) outline points in undistorted
    full-size pixels, ``outline_valid`` (F, V, B) bool; ``valid`` (F, V) views with a mask; ``sizes`` (V, 2) full-size
    and ``reduced`` (V, 2) reduced (width, height) of each view."""

    distance: torch.Tensor
    outline: torch.Tensor
    outline_valid: torch.Tensor
    valid: torch.Tensor
    sizes: torch.Tensor
    reduced: torch.Tensor


def distance_to_mask(mask: np.ndarray) -> np.ndarray:
    """(h, w) float32 Euclidean distance (px) from each pixel to the nearest pixel of the (h, w) bool ``mask`` (0 on
    it; inf when the mask is empty), the same bits on every call.

    OpenCV's exact transform (``DIST_L2``, ``DIST_MASK_PRECISE``) returns sqrt(k) for the integer squared distance k,
    but to within an ulp that changes with where its buffers lie in memory (measured: docs/results/faults.md), and a
    body fit carries an ulp to percents. Squaring and rounding recovers k exactly while its error, about
    2 d^2 2^-23, stays below 0.5, i.e. for d < 1,448 px (farther distances keep at most that rounding); the square
    root of k in float64 is then rounded once to float32 (``scipy.ndimage.distance_transform_edt``'s figures)."""
    if not mask.any():
        return np.full(mask.shape, np.inf, np.float32)
    field = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.sqrt(np.rint(np.square(field, dtype=np.float64))).astype(np.float32)


def mask_outline(mask: np.ndarray, count: int) -> np.ndarray:
    """Up to ``count`` points (x, y) evenly spaced along the mask's outer contours (reduced pixels)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    points = np.concatenate([c[:, 0] for c in contours]) if contours else np.zeros((0, 2))
    if len(points) > count:
        points = points[np.linspace(0, len(points) - 1, count).astype(int)]
    return points.astype(np.float32)


def silhouette_targets(cameras, masks, settings: SilhouetteSettings, unknown=None) -> SilhouetteTargets:
    """Targets of :class:`SilhouetteTargets` from ``masks[f][v]``: undistorted masks reduced to at most
    ``settings.height`` rows (``(h, w)`` bool), or None; ``cameras[v]``: anything with the full-size ``width`` and
    ``height`` of view v's pixels (a ``Camera``). ``unknown[f][v]`` (the masks' shapes, or None): pixels whose owner
    is unknown (somebody in front of the person): the body may lie there (the outside term counts them as mask),
    and the mask's outline along them is no outline of the person (the inside term leaves those points out)."""
    n_frames, n_views = len(masks), len(cameras)
    shapes = [next((m[v].shape for m in masks if m[v] is not None), (1, 1)) for v in range(n_views)]
    h, w = max(s[0] for s in shapes), max(s[1] for s in shapes)
    distance = torch.ones(n_frames, n_views, h, w)
    outline = torch.zeros(n_frames, n_views, settings.outline_points, 2)
    outline_valid = torch.zeros(n_frames, n_views, settings.outline_points, dtype=torch.bool)
    valid = torch.zeros(n_frames, n_views, dtype=torch.bool)
    for f, row in enumerate(masks):
        for v, mask in enumerate(row):
            if mask is None or not mask.any():
                continue
            rows, cols = mask.shape
            hidden = None if unknown is None else unknown[f][v]
            covered = mask if hidden is None else mask | hidden
            distance[f, v, :rows, :cols] = torch.as_tensor(distance_to_mask(covered) / rows)
            points = mask_outline(mask, settings.outline_points)
            if hidden is not None and hidden.any():  # outline points next to unknown pixels are left out
                beside = cv2.dilate(hidden.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
                points = points[~beside[points[:, 1].astype(int), points[:, 0].astype(int)]]
            ratio = cameras[v].height / rows  # reduced pixel centres to full-size pixels
            outline[f, v, : len(points)] = torch.as_tensor((points + 0.5) * ratio - 0.5)
            outline_valid[f, v, : len(points)] = True
            valid[f, v] = True
    sizes = torch.tensor([[c.width, c.height] for c in cameras], dtype=torch.float32)
    reduced = torch.tensor([[s[1], s[0]] for s in shapes], dtype=torch.float32)
    return SilhouetteTargets(distance, outline, outline_valid, valid, sizes, reduced)


def robust(r: torch.Tensor) -> torch.Tensor:
    return r**2 / (r**2 + 1)


class SilhouetteTerm:
    """``E_out + E_in`` (module docstring) of posed vertices, for fixed targets and projections."""

    def __init__(self, targets: SilhouetteTargets, P: np.ndarray, settings: SilhouetteSettings):
        self.targets, self.settings = targets, settings
        self.P = torch.as_tensor(P, dtype=torch.float32)
        self.nearest: torch.Tensor | None = None
        self.calls = 0

    def project(self, vertices: torch.Tensor, P: torch.Tensor | None = None) -> torch.Tensor:
        """(F, N, 3) world vertices -> (F, V, N, 2) undistorted full-size pixels (``P``: other projections)."""
        homogeneous = torch.cat([vertices, torch.ones_like(vertices[..., :1])], dim=-1)
        image = torch.einsum("vij,fnj->fvni", self.P if P is None else P, homogeneous)
        return image[..., :2] / image[..., 2:].clamp(min=1e-3)

    def __call__(self, vertices: torch.Tensor, P: torch.Tensor | None = None, strided: bool = False) -> torch.Tensor:
        """The term for (F, N, 3) posed vertices, seen by the cameras' projections ``P`` (V, 3, 4) (None: the ones
        given at construction). ``strided``: ``vertices`` are already every ``vertex_stride``-th vertex of the body
        (``BodyModel.vertices_zju(..., every=vertex_stride)``, which poses only those)."""
        t, s = self.targets, self.settings
        pixels = self.project(vertices if strided else vertices[:, :: s.vertex_stride], P)  # (F, V, N, 2)
        n_frames, n_views = pixels.shape[:2]
        heights = t.sizes[:, 1]
        # full-size pixel x lies at (x + 0.5) r / R - 0.5 in a view reduced from R to r pixels; grid_sample
        # (align_corners=False) reads the padded (h, w) tensor at g = (2 p + 1) / w - 1
        h, w = t.distance.shape[-2:]
        factor = 2 * t.reduced / (t.sizes * torch.tensor([w, h], dtype=torch.float32))  # (V, 2)
        grid = (pixels + 0.5) * factor[None, :, None] - 1
        sampled = F.grid_sample(
            t.distance.reshape(-1, 1, h, w),
            grid.reshape(n_frames * n_views, 1, -1, 2),
            align_corners=False,
            padding_mode="border",
        ).reshape(n_frames, n_views, -1)
        weight = t.valid.float()
        outside = (weight[..., None] * robust(sampled / s.scale)).mean(-1).sum() / weight.sum().clamp(min=1)
        if self.nearest is None or self.calls % s.nearest_every == 0:
            self.nearest = nearest_points(t.outline.flatten(0, 1), pixels.detach().flatten(0, 1))
        self.calls += 1
        index = self.nearest.reshape(n_frames, n_views, -1, 1).expand(-1, -1, -1, 2)
        gap = (pixels.gather(2, index) - t.outline).norm(dim=-1) / heights[None, :, None]
        valid = t.outline_valid.float()
        inside = (valid * robust(gap / s.scale)).sum() / valid.sum().clamp(min=1)
        return outside + inside


def nearest_points(queries: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(B, M) long: for each of the (B, M, 2) ``queries``, the index of the nearest of the (B, N, 2) ``points`` of
    the same batch entry (Euclidean; a k-d tree per entry, in float64). :func:`nearest_points_reference`, the full
    distance matrix, is its oracle (and was the search: 0.27 s for 40 views of 3,445 vertices)."""
    found = [cKDTree(p).query(q)[1] for q, p in zip(queries.double().numpy(), points.double().numpy())]
    return torch.as_tensor(np.stack(found), dtype=torch.long).reshape(queries.shape[:2])


def nearest_points_reference(queries: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """:func:`nearest_points` by the full (B, M, N) float64 distance matrix."""
    return torch.cdist(queries.double(), points.double()).argmin(-1)


def adam_stage(energy, variables: list[torch.Tensor], iterations: int, lr: float, tick=None) -> None:
    """``iterations`` Adam steps on ``energy()`` over ``variables``, the rate annealed (cosine) to 5 % of ``lr``;
    ``tick()`` after each."""
    optimiser = torch.optim.Adam(variables, lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, iterations, eta_min=lr * 0.05)
    for _ in range(iterations):
        optimiser.zero_grad()
        energy().backward()
        optimiser.step()
        schedule.step()
        if tick is not None:
            tick()
