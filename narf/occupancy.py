"""Empty-space skipping with a per-part occupancy grid (docs/model.md §5, "Occupancy grid").

Every part box holds an N^3 grid over its box coordinates u in [-1, 1]^3 (the coordinates the fields already use):
cell c of part i stores the largest density sigma seen at a point of that cell, refreshed during fitting from the
field itself (as instant-NGP does: a refreshed cell takes max(decay * old, new); cells start at +inf, i.e.
occupied).
A world point is occupied when some part box containing it has an occupied cell there (sigma above a threshold,
dilated by one cell so that a surface sampled between cell centres is not lost).

The renderer keeps its sampling; only the ray interval changes: ``occupied_bounds`` marches each ray through the
grid and narrows [near, far] to the first and last occupied march point (one march step of margin each side); rays
with no occupied point are treated as misses. Where the grid is fully occupied the bounds are the box bounds, i.e.
the dense reference exactly.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from narf.fields.common import PoseBatch
from narf.rays import ray_box_intersect, ray_box_slabs, union_bounds


def cell_index(u: torch.Tensor, resolution: int) -> torch.Tensor:
    """Cell index (..., 3) long of box coordinates u (..., 3) in an N^3 grid over [-1, 1]^3, clamped to the grid."""
    return ((u + 1) * (resolution / 2)).floor().long().clamp(0, resolution - 1)


def flat_cell_index(u: torch.Tensor, part: torch.Tensor, resolution: int, n_parts: int) -> torch.Tensor:
    """The cell of :func:`cell_index` as one index into the flattened (n_parts, N, N, N) grid: u (..., 3) box
    coordinates of part ``part`` (broadcast against u[..., 0]) -> (...) long.

    Computed in floating point and converted to integers once, which is exact while every index is an integer below
    2^24 (float32; float64 above) and faster than indexing with four integer tensors (docs/results/benchmark.md).
    NaN coordinates give index 0 (masked by every caller: a NaN point is in no box).
    """
    n = resolution
    dtype = torch.float32 if n_parts * n**3 <= 2**24 and u.dtype != torch.float64 else torch.float64
    cells = ((u.to(dtype) + 1) * (n / 2)).floor_().clamp_(0, n - 1)
    flat = (cells[..., 0] * n + cells[..., 1]) * n + cells[..., 2] + part.to(dtype) * n**3
    return flat.long().clamp_(0, n_parts * n**3 - 1)


class OccupancyGrid(nn.Module):
    """Per-part density maxima over box-coordinate cells.

    Args:
        n_parts: P. resolution: N cells per axis. threshold: sigma (per world unit of depth) below which a cell is
            empty; the default 0.5 loses at most 1 - exp(-0.5 * 0.02) = 1 % opacity over 2 cm, about the spacing of
            the CPU preset's coarse samples on a body-sized interval (docs/model.md §5).
        decay: factor on a refreshed cell's previous value (0.5: a cell whose density has gone falls below the
            threshold within about 8 refreshes from sigma ~ 100, while a cell re-measured occupied stays so).
    """

    def __init__(self, n_parts: int, resolution: int = 24, threshold: float = 0.5, decay: float = 0.5):
        super().__init__()
        if resolution < 2:
            raise ValueError(f"occupancy resolution must be at least 2, got {resolution}")
        self.resolution, self.threshold, self.decay = resolution, threshold, decay
        self.register_buffer("density", torch.full((n_parts,) + (resolution,) * 3, float("inf")))
        self._occupied: torch.Tensor | None = None  # cache of occupied(), cleared by update() and loading

    def occupied(self) -> torch.Tensor:
        """(P, N, N, N) bool: density above the threshold, dilated by one cell (3^3 max filter)."""
        if self._occupied is None or self._occupied.device != self.density.device:
            above = (self.density > self.threshold).float()[:, None]
            self._occupied = F.max_pool3d(above, kernel_size=3, stride=1, padding=1)[:, 0] > 0
        return self._occupied

    def _load_from_state_dict(self, *args, **kwargs):
        self._occupied = None
        super()._load_from_state_dict(*args, **kwargs)

    def update(self, parts: torch.Tensor, cells: torch.Tensor, sigma: torch.Tensor) -> None:
        """cell <- max(decay * cell, sigma) for the refreshed cells (each listed once).

        Args:
            parts: (M,) long. cells: (M, 3) long. sigma: (M,) densities measured in those cells.
        """
        i, j, k = cells.unbind(-1)
        old = self.density[parts, i, j, k]
        old = torch.where(torch.isinf(old), torch.zeros_like(old), old * self.decay)
        self.density[parts, i, j, k] = torch.maximum(old, sigma.to(old.dtype))
        self._occupied = None

    def occupied_fraction(self) -> float:
        return float(self.occupied().float().mean())


def occupied_bounds(
    occupied: torch.Tensor,
    o_box: torch.Tensor,
    d_box: torch.Tensor,
    t_in: torch.Tensor,
    t_out: torch.Tensor,
    hits: torch.Tensor,
    n_steps: int = 64,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Narrow the box bounds of rays to their occupied stretch.

    The union bounds [near, far] (:func:`narf.rays.ray_box_intersect`) are cut into K segments of length dt, with
    midpoints t_k. Segment k is occupied if, for some box i whose interval [t_in_i, t_out_i] it overlaps, the cell
    of that box at the clamped depth clamp(t_k, t_in_i, t_out_i) is occupied (the clamp keeps boxes thinner than a
    segment). near' = max(near, t_first - dt), far' = min(far, t_last + dt); hit' = hit and some segment is occupied.
    With every cell occupied this returns the union bounds unchanged. Only the (ray, box) pairs that hit are
    marched.

    Args:
        occupied: (P, N, N, N) bool (``OccupancyGrid.occupied``). o_box, d_box, t_in, t_out, hits: the per-box slab
            test (:func:`narf.rays.ray_box_slabs`), (R, P, 3) and (R, P). n_steps: K.

    Returns:
        near (R,), far (R,), hit (R,) bool.
    """
    near, far, hit = union_bounds(t_in, t_out, hits)
    if not hit.any():
        return near, far, hit
    step = (far - near) / n_steps  # (R,)
    ks = torch.arange(n_steps, dtype=near.dtype, device=near.device) + 0.5
    ray, part = hits.nonzero().unbind(-1)  # (M,) hit pairs
    depths = near[ray, None] + ks * step[ray, None]  # (M, K)
    low, high = t_in[ray, part, None], t_out[ray, part, None]
    half_step = step[ray, None] / 2
    overlaps = (depths + half_step >= low) & (depths - half_step <= high)
    t = torch.minimum(torch.maximum(depths, low), high)
    u = o_box[ray, part, None] + t[..., None] * d_box[ray, part, None]  # (M, K, 3)
    cell = flat_cell_index(u, part[:, None], occupied.shape[-1], occupied.shape[0])
    marked_pairs = occupied.reshape(-1)[cell] & overlaps  # (M, K)
    marked = torch.zeros(hits.shape[0], n_steps, dtype=near.dtype, device=near.device)
    marked = marked.index_add(0, ray, marked_pairs.to(near.dtype)) > 0  # (R, K)
    any_marked = marked.any(dim=-1)
    first = marked.float().argmax(dim=-1)
    last = n_steps - 1 - marked.flip(-1).float().argmax(dim=-1)
    new_near = torch.maximum(near, near + (first + 0.5) * step - step)
    new_far = torch.minimum(far, near + (last + 0.5) * step + step)
    near = torch.where(any_marked, new_near, torch.zeros_like(near))
    far = torch.where(any_marked, new_far, torch.zeros_like(far))
    return near, far, any_marked


def grid_density(grid: OccupancyGrid, u: torch.Tensor, ceiling: float = 1e4) -> torch.Tensor:
    """The grid's density at sample points: sigma_grid = max over the parts whose box contains the point of the
    stored density of that part's cell there; 0 outside every box. Cells never measured (+inf) read as ``ceiling``
    (opaque, as the grid treats them: occupied).

    Args:
        grid: an OccupancyGrid. u: (R, S, P, 3) box coordinates of the samples in every part box.

    Returns:
        (R, S) densities.
    """
    in_box = u.abs().amax(dim=-1) <= 1
    n_parts = u.shape[-2]
    cell = flat_cell_index(u, torch.arange(n_parts, device=u.device), grid.resolution, n_parts)
    values = grid.density.reshape(-1)[cell].clamp_max(ceiling).to(u.dtype)
    return torch.where(in_box, values, torch.zeros_like(values)).amax(dim=-1)


def refresh_cells(
    grid: OccupancyGrid,
    density_fn,
    poses: PoseBatch,
    box_centres: torch.Tensor,
    box_half_extents: torch.Tensor,
    cells: torch.Tensor,
    generator: torch.Generator,
    chunk: int = 16384,
) -> None:
    """Measure the density at one jittered point of each listed cell and update the grid; each chunk of cells is
    placed in the world by one random frame of ``poses`` (so the field evaluates it as one ray of many samples).

    Args:
        grid: the OccupancyGrid. density_fn: (points (M, 3), frame) -> sigma (M,) under that frame's pose.
        poses: the fit's training poses (F frames). box_centres, box_half_extents: (P, 3).
        cells: (M,) flat indices into (P, N, N, N). generator: CPU generator for the jitter and the frames.
    """
    n = grid.resolution
    device = box_centres.device
    for start in range(0, cells.numel(), chunk):
        flat = cells[start : start + chunk]
        part, rest = flat // n**3, flat % n**3
        index = torch.stack([rest // (n * n), (rest // n) % n, rest % n], dim=-1)
        jitter = torch.rand(flat.numel(), 3, generator=generator).to(device, box_centres.dtype)
        u = (index.to(box_centres.dtype) + jitter) * (2 / n) - 1
        frame = int(torch.randint(0, poses.reach.shape[0], (1,), generator=generator))
        x_local = box_centres[part] + u * box_half_extents[part]
        world_from_part = poses.world_from_part[frame, part]
        points = (
            torch.einsum("mij,mj->mi", world_from_part[:, :3, :3], x_local * poses.reach[frame])
            + world_from_part[:, :3, 3]
        )
        with torch.no_grad():
            sigma = density_fn(points, frame)
        grid.update(part, index, sigma)


def field_ray_bounds(
    field, origins: torch.Tensor, dirs: torch.Tensor, pose: PoseBatch, n_steps: int = 64
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Ray bounds of a field: the slab test against its part boxes, narrowed by its occupancy grid when it has one
    (``field.occupancy``; see the module docstring).

    Args:
        field: a Field. origins, dirs: (R, 3). pose: per-ray PoseBatch (R entries). n_steps: march points per ray.

    Returns:
        near (R,), far (R,), hit (R,) bool.
    """
    boxes = (pose.world_from_part, pose.reach, field.box_centres, field.box_half_extents)
    grid = getattr(field, "occupancy", None)
    if grid is None:
        return ray_box_intersect(origins, dirs, *boxes)
    return occupied_bounds(grid.occupied(), *ray_box_slabs(origins, dirs, *boxes), n_steps)
