"""Sparse Levenberg-Marquardt for bundle adjustment: grouped finite-difference Jacobian, Huber weights.

``scipy.optimize.least_squares`` with a sparse Jacobian solves each trust-region step iteratively (LSMR); on
a 21-camera rig with ~250 board poses it needs hundreds of steps and stops at its evaluation limit before
converging. Here each step solves the (small: a few thousand unknowns) sparse normal equations directly, and a
Jacobian costs one pair of residual evaluations per column group (columns that share no residual row are
perturbed together, so ~20 groups for a rig instead of ~1700 columns). ``tests/test_sparse_lm.py``
checks the Jacobian against plain column-by-column differences and the minimum against ``least_squares``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.linalg


@dataclass
class LmResult:
    """Solution ``x``, its robust cost, the iterations taken and whether the relative cost change fell below
    the tolerance (else the iteration limit was hit)."""

    x: np.ndarray
    cost: float
    iterations: int
    converged: bool


def column_groups(sparsity: scipy.sparse.spmatrix) -> np.ndarray:
    """(M,) group index per column; columns of one group share no row of the (R, M) ``sparsity`` pattern."""
    pattern = scipy.sparse.csc_matrix(sparsity, dtype=bool)
    occupied: list[np.ndarray] = []
    groups = np.empty(pattern.shape[1], dtype=np.int64)
    for col in range(pattern.shape[1]):
        rows = pattern.indices[pattern.indptr[col] : pattern.indptr[col + 1]]
        free = [g for g, used in enumerate(occupied) if not used[rows].any()]
        if not free:
            occupied.append(np.zeros(pattern.shape[0], dtype=bool))
        group = free[0] if free else len(occupied) - 1
        occupied[group][rows] = True
        groups[col] = group
    return groups


def sparse_jacobian(
    fun: Callable[[np.ndarray], np.ndarray],
    x: np.ndarray,
    sparsity: scipy.sparse.spmatrix,
    groups: np.ndarray,
    rel_step: float = 1e-6,
) -> scipy.sparse.csr_matrix:
    """(R, M) central-difference Jacobian of ``fun`` at ``x`` with the given pattern and column groups."""
    pattern = scipy.sparse.coo_matrix(sparsity)
    step = rel_step * np.maximum(1.0, np.abs(x))
    diffs = []
    for g in range(int(groups.max()) + 1):
        delta = np.where(groups == g, step, 0.0)
        diffs.append(fun(x + delta) - fun(x - delta))
    values = np.stack(diffs)[groups[pattern.col], pattern.row] / (2.0 * step[pattern.col])
    return scipy.sparse.csr_matrix((values, (pattern.row, pattern.col)), shape=pattern.shape)


def _huber(residuals: np.ndarray, point_dim: int, delta: float) -> tuple[float, np.ndarray]:
    """Robust cost and per-residual IRLS weights, Huber on the norm of each ``point_dim``-vector."""
    norms = np.linalg.norm(residuals.reshape(-1, point_dim), axis=1)
    cost = np.where(norms <= delta, 0.5 * norms**2, delta * norms - 0.5 * delta**2).sum()
    weights = np.where(norms <= delta, 1.0, delta / np.maximum(norms, 1e-300))
    return float(cost), np.repeat(weights, point_dim)


def solve_sparse_lm(
    fun: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
    sparsity: scipy.sparse.spmatrix,
    huber: float = 1.0,
    point_dim: int = 2,
    max_iter: int = 100,
    tol: float = 1e-10,
) -> LmResult:
    """Minimise sum(Huber(|r_i|)) over the ``point_dim``-vectors r_i of ``fun(x)`` from ``x0``.

    Levenberg-Marquardt with Marquardt's diagonal scaling on iteratively reweighted normal equations.
    """
    groups = column_groups(sparsity)
    x = np.asarray(x0, dtype=np.float64).copy()
    residuals = fun(x)
    cost, weights = _huber(residuals, point_dim, huber)
    damping, converged, iteration = 1e-3, False, 0
    for iteration in range(1, max_iter + 1):
        jac = sparse_jacobian(fun, x, sparsity, groups)
        weighted = scipy.sparse.diags(weights) @ jac
        normal = (jac.T @ weighted).tocsc()
        gradient = weighted.T @ residuals
        scale = np.maximum(normal.diagonal(), 1e-12)
        while True:
            system = (normal + scipy.sparse.diags(damping * scale)).tocsc()
            step = scipy.sparse.linalg.spsolve(system, -gradient)
            new_residuals = fun(x + step)
            new_cost, new_weights = _huber(new_residuals, point_dim, huber)
            if new_cost < cost:
                break
            damping *= 4.0
            if damping > 1e12:
                return LmResult(x, cost, iteration, True)  # no descent left: at the minimum to precision
        converged = cost - new_cost <= tol * cost
        x, residuals, cost, weights = x + step, new_residuals, new_cost, new_weights
        damping = max(damping / 3.0, 1e-12)
        if converged:
            break
    return LmResult(x, cost, iteration, converged)
