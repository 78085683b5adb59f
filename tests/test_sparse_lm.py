"""The sparse Levenberg-Marquardt solver against hand-computed Jacobians and scipy's least_squares."""

import numpy as np
import scipy.sparse
from scipy.optimize import least_squares

from pipelines.calibration.sparse_lm import column_groups, solve_sparse_lm, sparse_jacobian

N_CURVES, N_SAMPLES = 6, 15


def _curves_problem(seed: int = 0):
    """K exponential curves y = a_k exp(b_k t) + c with a shared offset c; parameters [a_0, b_0, ..., c]."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, N_SAMPLES)
    truth = np.concatenate([np.stack([rng.uniform(1, 2, N_CURVES), rng.uniform(-1, 1, N_CURVES)], 1).ravel(), [0.3]])
    a, b, c = truth[0:-1:2], truth[1:-1:2], truth[-1]
    y = a[:, None] * np.exp(b[:, None] * t) + c + rng.normal(0, 0.01, (N_CURVES, N_SAMPLES))
    y[1, 3] += 2.0  # outliers, for the robust loss
    y[4, 9] -= 3.0

    def fun(x):
        return (x[0:-1:2, None] * np.exp(x[1:-1:2, None] * t) + x[-1] - y).ravel()

    def analytic_jacobian(x):
        jac = np.zeros((N_CURVES * N_SAMPLES, len(x)))
        for k in range(N_CURVES):
            rows = slice(k * N_SAMPLES, (k + 1) * N_SAMPLES)
            jac[rows, 2 * k] = np.exp(x[2 * k + 1] * t)
            jac[rows, 2 * k + 1] = x[2 * k] * t * np.exp(x[2 * k + 1] * t)
            jac[rows, -1] = 1.0
        return jac

    sparsity = analytic_jacobian(np.ones_like(truth)) != 0
    return fun, analytic_jacobian, sparsity, truth


def test_column_groups_share_no_row():
    _, _, sparsity, _ = _curves_problem()
    groups = column_groups(scipy.sparse.csr_matrix(sparsity))
    for g in np.unique(groups):
        assert sparsity[:, groups == g].sum(axis=1).max() <= 1
    assert groups.max() + 1 == 3  # every a_k together, every b_k together, then c alone


def test_grouped_jacobian_matches_the_analytic_one():
    fun, analytic, sparsity, truth = _curves_problem()
    x = truth + 0.05
    groups = column_groups(scipy.sparse.csr_matrix(sparsity))
    jac = sparse_jacobian(fun, x, scipy.sparse.csr_matrix(sparsity), groups).toarray()
    # central differences: truncation ~h^2 f''' / 6 and rounding ~eps64 |f| / h; at the solver's step
    # (h ~ eps^(1/3) ~ 6e-6) both are ~1e-10 to 1e-11 for these smooth O(1) curves
    assert np.allclose(jac, analytic(x), atol=1e-7, rtol=1e-7)


def test_minimum_matches_scipy_least_squares_with_huber_loss():
    fun, analytic, sparsity, truth = _curves_problem()
    x0 = np.concatenate([np.tile([1.0, 0.0], N_CURVES), [0.0]])
    ours = solve_sparse_lm(fun, x0, scipy.sparse.csr_matrix(sparsity), huber=0.05, point_dim=1, tol=1e-14)
    reference = least_squares(
        fun, x0, jac=analytic, loss="huber", f_scale=0.05, method="trf", xtol=1e-15, ftol=1e-15, gtol=1e-15
    )
    assert ours.converged
    # both solvers stop at tolerances ~1e-14; the minimum of this well-conditioned problem is then fixed to ~1e-8
    # by the finite-difference Jacobian's error (1e-10) times the inverse curvature (~1e2)
    assert np.allclose(ours.x, reference.x, atol=1e-6)
    assert np.abs(ours.x - truth).max() < 0.05  # and the outliers did not drag the fit away
