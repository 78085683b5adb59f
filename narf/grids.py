"""Learned multi-resolution grids in the part frames (docs/model.md §2, *Part grids*).

Each part i owns L grids over its box coordinates u in [-1, 1]^3. Level l has N_l cells per axis,
N_l = floor(N_min b^l) with b = (N_max / N_min)^(1 / (L - 1)), and a table of T rows of F features: a level whose
(N_l + 1)^3 vertices fit in T rows stores them one to one, a finer one hashes them (Instant-NGP, Müller et al.
2022, eq. 4): h(v) = (v_x * 1 xor v_y * 2654435761 xor v_z * 805459861) mod T. The features of a point are the
trilinear blend of its cell's 8 vertices at every level, concatenated level by level:

    g_i(u) = [sum_c w_c(x_l) table[l, i, h_l(floor(x_l) + c)]]_{l < L},  x_l = (u + 1) / 2 * N_l,

with c over the cell's corners {0, 1}^3 and w_c the trilinear weights. The tables are one tensor, level-major:
(L, P, T, F), flattened to (L P T, F) rows. :func:`grid_features` is the fast path (one ``embedding_bag``: the
8-corner gather and the weighted sum in one kernel, its backward one scatter-add, no loop over levels or parts);
:func:`grid_features_reference` the slow, obvious loop over parts, levels and corners, its test oracle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from narf.encodings import frequency_window

#: Instant-NGP's hash primes (the first is 1, so that a level's x coordinate strides through the table)
HASH_PRIMES = (1, 2654435761, 805459861)
#: the 8 corners of a cell, (8, 3) in {0, 1}, x fastest
CORNERS = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])


@dataclass(frozen=True)
class GridShape:
    """The sizes of the part grids: ``levels`` L, ``features`` F per level, the coarsest and finest cells per axis
    ``min_resolution`` N_min and ``max_resolution`` N_max, and ``log2_rows`` log2 T (rows per level and part)."""

    levels: int = 8
    features: int = 2
    min_resolution: int = 8
    max_resolution: int = 128
    log2_rows: int = 12

    def __post_init__(self):
        if self.levels < 1 or self.features < 1:
            raise ValueError(f"grid levels and features must be >= 1, got {self.levels}, {self.features}")
        if not 1 <= self.min_resolution <= self.max_resolution:
            raise ValueError(
                f"grid resolutions: need 1 <= min <= max, got {self.min_resolution}, {self.max_resolution}"
            )
        if not 4 <= self.log2_rows <= 24:
            raise ValueError(f"grid log2_rows must be in [4, 24], got {self.log2_rows}")

    @property
    def rows(self) -> int:
        """T, the rows of one level of one part."""
        return 1 << self.log2_rows

    @property
    def width(self) -> int:
        """L F, the features of one point in one part."""
        return self.levels * self.features

    def resolutions(self) -> list[int]:
        """N_l for l < L (cells per axis)."""
        if self.levels == 1:
            return [self.min_resolution]
        growth = (self.max_resolution / self.min_resolution) ** (1 / (self.levels - 1))
        return [int(math.floor(self.min_resolution * growth**level + 1e-6)) for level in range(self.levels)]

    def axis_bits(self) -> list[int]:
        """Per level: b_l = ceil(log2(N_l + 1)), the bits of one axis's vertex index."""
        return [int(n).bit_length() for n in self.resolutions()]

    def hashed(self) -> list[bool]:
        """Per level: whether its vertices, at 2^b_l rows per axis, exceed the table's T rows (then they are hashed)."""
        return [3 * bits > self.log2_rows for bits in self.axis_bits()]

    def multipliers(self) -> list[tuple[int, int, int]]:
        """Per level, what each axis's vertex index is multiplied by before the three are combined by xor: 1, 2^b,
        2^2b (one to one: the xor of disjoint bit fields is x + 2^b y + 2^2b z) or the hash primes."""
        return [
            HASH_PRIMES if hashed else (1, 1 << bits, 1 << (2 * bits))
            for bits, hashed in zip(self.axis_bits(), self.hashed())
        ]


def vertex_rows(vertex: torch.Tensor, multipliers, rows: int) -> torch.Tensor:
    """The table row of integer vertices (..., 3) long: (v_x m_x xor v_y m_y xor v_z m_z) mod T, with a level's
    :meth:`GridShape.multipliers` m (3,), or every level's (L, 3) against vertices (..., L, 3) (one to one:
    x + 2^b y + 2^2b z; hashed: Instant-NGP's hash)."""
    terms = vertex * torch.as_tensor(multipliers, dtype=torch.long, device=vertex.device)
    return torch.bitwise_xor(torch.bitwise_xor(terms[..., 0], terms[..., 1]), terms[..., 2]) & (rows - 1)


def corner_rows_and_weights(u: torch.Tensor, part: torch.Tensor, shape: GridShape, n_parts: int):
    """Rows and trilinear weights of the 8 corners of each point's cell at every level, corner-major.

    The work is done per axis on (3, M, L) tensors, and the 8 corners are formed by broadcasting the three axes'
    (2, M, L) parts against each other (leading dimensions, so every kernel runs over long contiguous rows): an xor of
    the row parts (:func:`vertex_rows`; only the low log2 T bits of a product reach the row, so each axis is reduced
    mod T first) and a product of the weights.

    Args:
        u: (M, 3) box coordinates (clamped to [-1, 1]). part: (M,) long part of each point.

    Returns:
        rows (8, M, L) long into the flat (L P T, F) table, weights (8, M, L) in u's dtype (differentiable in u);
        corner c = x + 2 y + 4 z (:data:`CORNERS`).
    """
    resolutions = torch.tensor(shape.resolutions(), dtype=u.dtype, device=u.device)
    multipliers = torch.tensor(shape.multipliers(), dtype=torch.long, device=u.device).T[:, None, :]  # (3, 1, L)
    x = (u.clamp(-1, 1).T[:, :, None] + 1) * (0.5 * resolutions)  # (3, M, L)
    base = x.detach().floor().clamp_max(resolutions - 1)  # the far face belongs to the last cell
    frac = x - base  # gradient through x
    low = base.long() * multipliers & (shape.rows - 1)  # (3, M, L)
    high = (base.long() + 1) * multipliers & (shape.rows - 1)
    # the table's offset of (level, part), a multiple of T, has no bit below log2 T: the xor carries it unchanged,
    # so it is added to the x parts (2, M, L) once, not to the 8 corners
    offset = (torch.arange(shape.levels, device=u.device) * n_parts + part[:, None]) * shape.rows  # (M, L)
    tx = torch.stack([low[0] + offset, high[0] + offset])  # (2, M, L)
    ty, tz = (torch.stack([low[a], high[a]]) for a in (1, 2))
    rows = torch.bitwise_xor(torch.bitwise_xor(tz[:, None, None], ty[None, :, None]), tx[None, None, :])
    rows = rows.reshape(8, *x.shape[1:])
    wx, wy, wz = (torch.stack([1 - frac[a], frac[a]]) for a in range(3))
    weights = (wz[:, None, None] * wy[None, :, None] * wx[None, None, :]).reshape(8, *x.shape[1:])
    return rows, weights


class _BlendRows(torch.autograd.Function):
    """out[n] = sum_c w[c, n] table[rows[c, n]] for N bags of 8 corners c, given corner-major (8, N): the forward is
    ``embedding_bag`` (the gather and the weighted sum in one kernel, on the bags' (N, 8) layout); the backward
    scatter-adds w[c, n] g[n] into the table's rows with one ``index_add_`` over the corner-major layout
    (``embedding_bag``'s own dense backward sorts the 8 N rows first, several times slower on a CPU); the weights'
    gradient g[n] . table[rows[c, n]] only when asked, and with N = M L bags laid out level fastest, only for the
    bags of the levels l < ``passing``: the others' is zero, so u's gradient passes the coarse levels only."""

    @staticmethod
    def forward(ctx, table, rows, weights, levels, passing):
        ctx.save_for_backward(table, rows, weights)
        ctx.levels, ctx.passing = levels, passing
        bags, bag_weights = rows.T.contiguous(), weights.T.contiguous()
        return nn.functional.embedding_bag(bags, table, per_sample_weights=bag_weights, mode="sum")

    @staticmethod
    def backward(ctx, grad):
        table, rows, weights = ctx.saved_tensors
        grad_table = grad_weights = None
        if ctx.needs_input_grad[0]:
            spread = (weights[:, :, None] * grad[None]).reshape(-1, table.shape[1]).to(table.dtype)
            grad_table = torch.zeros_like(table).index_add_(0, rows.reshape(-1), spread)
        if ctx.needs_input_grad[2]:
            levels, passing = ctx.levels, ctx.passing  # (8, M, L) bags: the passing levels' corners gathered only
            coarse_rows = rows.unflatten(1, (-1, levels))[:, :, :passing]
            coarse = (table[coarse_rows] * grad.unflatten(0, (-1, levels))[None, :, :passing]).sum(-1)
            grad_weights = nn.functional.pad(coarse, (0, levels - passing)).flatten(1).to(weights.dtype)
        return grad_table, None, grad_weights, None, None


def grid_features(
    table: torch.Tensor, u: torch.Tensor, part: torch.Tensor, shape: GridShape, gradient_levels: int | None = None
) -> torch.Tensor:
    """g_part(u) of M points: the fast path (one gather-and-blend over every level and part, one scatter-add back).

    Args:
        table: (L P T, F) level-major rows. u: (M, 3) box coordinates. part: (M,) long.
        gradient_levels: u's gradient passes through the levels l < gradient_levels only (None: all).

    Returns:
        (M, L F), level by level; gradients reach ``table`` (a scatter-add of the weighted output gradient) and
        ``u`` (through the trilinear weights).
    """
    n_parts = table.shape[0] // (shape.levels * shape.rows)
    m = u.shape[0]
    if m == 0:
        return table.new_zeros(0, shape.width)
    rows, weights = corner_rows_and_weights(u, part, shape, n_parts)  # (8, M, L): bags of (point, level)
    passing = shape.levels if gradient_levels is None else min(gradient_levels, shape.levels)
    out = _BlendRows.apply(table, rows.reshape(8, -1), weights.to(table.dtype).reshape(8, -1), shape.levels, passing)
    return out.reshape(m, shape.width)


def grid_features_reference(
    table: torch.Tensor, u: torch.Tensor, part: torch.Tensor, shape: GridShape, gradient_levels: int | None = None
) -> torch.Tensor:
    """The slow, obvious g_part(u): a loop over points' parts, levels and the 8 corners, the vertex's row from
    :func:`vertex_rows` and its weight the product of per-axis weights, the levels l >= ``gradient_levels`` reading
    u without its gradient. The test oracle of :func:`grid_features`."""
    n_parts = table.shape[0] // (shape.levels * shape.rows)
    tables = table.reshape(shape.levels, n_parts, shape.rows, shape.features)
    out = []
    for level, (resolution, multipliers) in enumerate(zip(shape.resolutions(), shape.multipliers())):
        passing = gradient_levels is None or level < gradient_levels
        x = ((u if passing else u.detach()).clamp(-1, 1) + 1) / 2 * resolution  # (M, 3)
        base = torch.clamp(torch.floor(x.detach()), max=resolution - 1)
        frac = x - base
        level_sum = torch.zeros(u.shape[0], shape.features, dtype=table.dtype, device=u.device)
        for corner in CORNERS.tolist():
            vertex = base.long() + torch.tensor(corner, device=u.device)
            weight = torch.ones(u.shape[0], dtype=u.dtype, device=u.device)
            for axis in range(3):
                weight = weight * (frac[:, axis] if corner[axis] else 1 - frac[:, axis])
            rows = vertex_rows(vertex, multipliers, shape.rows)
            level_sum = level_sum + weight[:, None].to(table.dtype) * tables[level, part, rows]
        out.append(level_sum)
    return torch.cat(out, dim=-1) if out else table.new_zeros(u.shape[0], 0)


def level_window(alpha: float | None, levels: int, device=None, dtype=torch.float32) -> torch.Tensor | None:
    """The coarse-to-fine weights of the grid levels at window position ``alpha`` in [0, L] (docs/model.md §2): the
    frequency window's half-cosine (``narf.encodings.frequency_window``) over levels; None when all are open."""
    if alpha is None or alpha >= levels:
        return None
    return frequency_window(alpha, levels, device, dtype)[:levels]  # laid out [sin k, cos k]: one half


class PartGrids(nn.Module):
    """The learned tables of every part's grids: one (L P T, F) parameter, initialised uniform in +-1e-4
    (Instant-NGP), so that a fresh field starts from its network's biases."""

    def __init__(self, n_parts: int, shape: GridShape):
        super().__init__()
        self.n_parts, self.shape = n_parts, shape
        rows = shape.levels * n_parts * shape.rows
        self.table = nn.Parameter(torch.empty(rows, shape.features).uniform_(-1e-4, 1e-4))

    def forward(
        self, u: torch.Tensor, part: torch.Tensor, alpha: float | None = None, gradient_levels: int | None = None
    ) -> torch.Tensor:
        """(M, 3) box coordinates and (M,) parts -> (M, L F) features, the levels past the window ``alpha`` faded,
        u's gradient through the levels l < ``gradient_levels`` only (None: all)."""
        features = grid_features(self.table, u, part, self.shape, gradient_levels)
        window = level_window(alpha, self.shape.levels, u.device, features.dtype)
        if window is None:
            return features
        return (features.unflatten(-1, (self.shape.levels, -1)) * window[:, None]).flatten(-2)


def grid_smoothness(table: torch.Tensor, shape: GridShape, vertices: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """The tables' total variation at K random vertices: mean over vertices and levels of
    |table[l, i, h_l(v)] - table[l, i, h_l(v + e_a)]|^2 (docs/model.md §2, *Part grids*), with v drawn per level.

    Args:
        table: (L P T, F). vertices: (K, L, 4) long, each row (part i, v_x, v_y, v_z) with v in [0, N_l - 1]^3.
        axis: (K, L) long in {0, 1, 2}, the neighbour's axis a.

    Returns:
        a scalar.
    """
    n_parts = table.shape[0] // (shape.levels * shape.rows)
    level = torch.arange(shape.levels, device=table.device)
    part, vertex = vertices[..., 0], vertices[..., 1:]
    neighbour = vertex + nn.functional.one_hot(axis, 3)

    def rows(v: torch.Tensor) -> torch.Tensor:  # (K, L, 3) -> (K, L) flat rows
        return vertex_rows(v, shape.multipliers(), shape.rows) + (level * n_parts + part) * shape.rows

    return (table[rows(vertex)] - table[rows(neighbour)]).square().sum(-1).mean()


def random_vertices(shape: GridShape, n_parts: int, count: int, generator: torch.Generator, device=None):
    """``count`` random (part, vertex) rows per level and a random axis each, for :func:`grid_smoothness`: parts
    uniform, each vertex uniform in [0, N_l - 1]^3 (so that its neighbour along any axis exists)."""
    resolutions = torch.tensor(shape.resolutions(), dtype=torch.float64)
    part = torch.randint(0, n_parts, (count, shape.levels, 1), generator=generator)
    vertex = (
        torch.rand(count, shape.levels, 3, generator=generator, dtype=torch.float64) * resolutions[:, None]
    ).long()
    axis = torch.randint(0, 3, (count, shape.levels), generator=generator)
    return torch.cat([part, vertex], dim=-1).to(device), axis.to(device)
