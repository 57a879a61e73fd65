"""OLS, WLS and TLS from triangular factors, checked against independent formulas."""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.errors import IdentificationError
from drivegain.identify.estimate import (
    cluster_sums,
    group_sigma_from_factor,
    ls_from_factor,
    ols,
    r_factor,
    stacked_factor,
    tls_covariance,
    tls_from_factor,
    tls_scores,
    wls,
)


def test_factor_of_stacked_blocks_is_factor_of_the_stack() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(40, 5)), rng.normal(size=(3, 5))  # b has fewer rows than columns
    r = stacked_factor([r_factor(a), r_factor(b)])
    full = np.vstack([a, b])
    np.testing.assert_allclose(r.T @ r, full.T @ full, rtol=1e-12, atol=1e-12)
    assert np.allclose(np.tril(r, -1), 0.0)


def test_ols_solution_and_eq_8_to_11() -> None:
    rng = np.random.default_rng(1)
    w = rng.normal(size=(200, 4)) * [1.0, 10.0, 0.1, 3.0]
    x_true = np.array([1.0, -2.0, 30.0, 0.5])
    y = w @ x_true + rng.normal(scale=0.3, size=200)
    res = ols(w, y)
    x_ref, *_ = np.linalg.lstsq(w, y, rcond=None)
    np.testing.assert_allclose(res.x, x_ref, rtol=1e-10)
    rho = y - w @ x_ref
    sigma2 = rho @ rho / (200 - 4)  # eq. (9)
    cov = sigma2 * np.linalg.inv(w.T @ w)  # eq. (10), explicit only as the independent check
    np.testing.assert_allclose(res.std, np.sqrt(np.diag(cov)), rtol=1e-9)
    np.testing.assert_allclose(res.cov, cov, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(res.rel_std_percent, 100 * res.std / np.abs(res.x))  # eq. (11)
    assert res.residual_norm == pytest.approx(np.linalg.norm(rho), rel=1e-10)


def test_wls_is_ols_on_rows_scaled_by_group_sigma() -> None:
    rng = np.random.default_rng(2)
    w = rng.normal(size=(120, 3))
    groups = np.repeat([0, 1, 2], 40)
    sigma = np.array([0.1, 1.0, 5.0])
    y = w @ [1.0, 2.0, 3.0] + rng.normal(size=120) * sigma[groups]
    res = wls(w, y, groups, sigma)
    ref = ols(w / sigma[groups][:, None], y / sigma[groups])
    np.testing.assert_allclose(res.x, ref.x, rtol=1e-12)
    np.testing.assert_allclose(res.std, ref.std, rtol=1e-12)


def test_ls_names_an_undetermined_parameter() -> None:
    rng = np.random.default_rng(3)
    w = rng.normal(size=(50, 3))
    w = np.column_stack([w, w[:, 0] + 2 * w[:, 1]])
    with pytest.raises(IdentificationError, match="dddd"):
        ols(w, rng.normal(size=50), names=["a", "b", "c", "dddd"])


def test_ls_needs_more_equations_than_unknowns() -> None:
    rng = np.random.default_rng(4)
    with pytest.raises(IdentificationError, match="equations"):
        ls_from_factor(r_factor(rng.normal(size=(3, 4))), 3)


def test_group_sigma_handles_zero_and_dependent_columns() -> None:
    rng = np.random.default_rng(5)
    base = rng.normal(size=(300, 2))
    w = np.column_stack([base, np.zeros(300), base[:, 0] - base[:, 1]])
    y = base @ [1.0, 2.0] + rng.normal(scale=0.5, size=300)
    fit = group_sigma_from_factor(r_factor(np.column_stack([w, y])), 300)
    ref = ols(base, y)
    assert fit.rank == 2
    assert fit.sigma == pytest.approx(ref.sigma, rel=1e-9)


def _tls_problem(rng: np.random.Generator, rows: int, noise: float) -> tuple[np.ndarray, ...]:
    a0 = rng.normal(size=(rows, 3)) * [1.0, 2.0, 0.5]
    theta = np.array([0.7, -1.2, 2.0])
    b0 = -(a0 @ theta)  # A0 [θ; 1] = 0 with last column b0
    a = np.column_stack([a0, b0]) + rng.normal(scale=noise, size=(rows, 4))
    return a, theta


def test_tls_matches_the_closed_form() -> None:
    rng = np.random.default_rng(6)
    a, _ = _tls_problem(rng, 500, 0.05)
    res = tls_from_factor(r_factor(a))
    assert res.x[-1] == 1.0
    s = np.linalg.svd(a, compute_uv=False)
    np.testing.assert_allclose(res.singular_values, s, rtol=1e-10)
    # Golub & Van Loan: θ = (AθᵀAθ − s²I)⁻¹ Aθᵀ b with b = −(last column).
    a_t, b = a[:, :-1], -a[:, -1]
    theta = np.linalg.solve(a_t.T @ a_t - s[-1] ** 2 * np.eye(3), a_t.T @ b)
    np.testing.assert_allclose(res.x[:-1], theta, rtol=1e-9)
    assert res.gap == pytest.approx(s[-2] / s[-1])
    assert res.theta_smin > s[-1]


def test_tls_refuses_a_solution_without_scale() -> None:
    rng = np.random.default_rng(7)
    a = rng.normal(size=(100, 4))
    a[:, 1] = 0.0  # an unknown the data do not see: the smallest singular vector has δ = 0
    with pytest.raises(IdentificationError, match="finite scale"):
        tls_from_factor(r_factor(a))


def test_tls_covariance_is_honest_in_monte_carlo() -> None:
    """Sandwich standard deviations against the spread of TLS estimates over noise draws."""
    rng = np.random.default_rng(8)
    a0, theta = _tls_problem(rng, 400, 0.0)
    thetas, stds = [], []
    for _ in range(400):
        a = a0 + rng.normal(scale=0.05, size=a0.shape)
        res = tls_from_factor(r_factor(a))
        psi = tls_scores(a, res.x)
        cov = tls_covariance(res, psi.T @ psi, a.shape[0], a.shape[0])
        thetas.append(res.x[:-1])
        stds.append(np.sqrt(np.diag(cov)))
    thetas, stds = np.array(thetas), np.array(stds)
    spread = thetas.std(axis=0)
    np.testing.assert_allclose(stds.mean(axis=0), spread, rtol=0.12)
    z = (thetas - theta) / stds
    coverage = np.mean(np.abs(z) < 2)
    assert 0.92 <= coverage <= 0.98


def test_cluster_sums() -> None:
    x = np.arange(6.0)[:, None]
    np.testing.assert_array_equal(cluster_sums(x, np.array([0, 1, 0, 2, 1, 0]), 3)[:, 0], [7, 5, 3])
