"""Covariance from the errors' autocovariance corrected for the fit (identify/autocov.py).

Checked three ways: against the whole-matrix formulas it streams (explicit shift and
projection matrices), block by block against one block, and against Monte Carlo on a linear
model whose errors are white noise decimated as a recording is (the process that motivated
it), where the plain lag-0 and Newey-West estimates are measurably too small.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.errors import UsageError
from drivegain.identify import autocov
from drivegain.identify.autocov import LaggedSums
from drivegain.identify.decimate import parallel_decimate
from drivegain.identify.hac import LongRunSum, sandwich


def _slow_design(rng: np.random.Generator, samples: int, n: int, p: int) -> np.ndarray:
    """(samples, n, p) regressors made of slow sines, as a regressor's columns are."""
    t = np.arange(samples)[:, None, None]
    freq = rng.uniform(0.002, 0.08, size=(1, n, p))
    phase = rng.uniform(0, 2 * np.pi, size=(1, n, p))
    return np.asarray(np.sin(2 * np.pi * freq * t + phase) * rng.uniform(0.5, 2.0, (1, n, p)))


def _decimated_noise(rng: np.random.Generator, samples: int, n: int) -> np.ndarray:
    """White noise at 20× the rate, low-passed and decimated by 20 (unit variance)."""
    trim = 10
    raw = rng.standard_normal(((samples + 2 * trim) * 20, n))
    (e,) = parallel_decimate([raw], 20, trim)
    return np.asarray(e / np.sqrt(np.mean(e**2)))


def _whole(jac: list[np.ndarray], resid: list[np.ndarray], lag: int) -> np.ndarray:
    """The covariance from explicit matrices: exact shifts, projection and trace formulas."""
    n, p = jac[0].shape[1], jac[0].shape[2]
    sizes = [j.shape[0] * n for j in jac]
    big_j = np.vstack([j.reshape(-1, p) for j in jac])
    big_e = np.concatenate([e.reshape(-1) for e in resid])
    h_inv = np.linalg.inv(big_j.T @ big_j)
    m = np.eye(sum(sizes)) - big_j @ h_inv @ big_j.T

    def v(d: int) -> np.ndarray:
        blocks = []
        for size in sizes:
            s = np.eye(size // n, k=d)
            blocks.append(np.kron(s + s.T if d else s, np.eye(n)))
        out = np.zeros((sum(sizes), sum(sizes)))
        at = 0
        for blk in blocks:
            out[at : at + blk.shape[0], at : at + blk.shape[0]] = blk
            at += blk.shape[0]
        return out

    vs = [v(d) for d in range(lag + 1)]
    us = [vs[0]] + [x / 2 for x in vs[1:]]
    q = np.array([big_e @ u @ big_e for u in us])
    a = np.array([[np.sum(u * (m @ x @ m)) for x in vs] for u in us])
    gamma = np.linalg.solve(a, q)
    omega = sum(g * x for g, x in zip(gamma, vs, strict=True))
    return np.asarray(h_inv @ big_j.T @ omega @ big_j @ h_inv)


def _streamed(jac: list[np.ndarray], resid: list[np.ndarray], lag: int, block: int):
    p = jac[0].shape[2]
    flat = np.vstack([j.reshape(-1, p) for j in jac])
    sums = LaggedSums(np.linalg.inv(flat.T @ flat), lag)
    for j, e in zip(jac, resid, strict=True):
        for start in range(0, j.shape[0], block):
            sums.add(j[start : start + block], e[start : start + block])
        sums.end_run()
    return sums.covariance()


def _fitted(rng: np.random.Generator, runs: int, samples: int, n: int, p: int):
    jac = [_slow_design(rng, samples, n, p) for _ in range(runs)]
    flat = np.vstack([j.reshape(-1, p) for j in jac])
    err = [_decimated_noise(rng, samples, n) for _ in range(runs)]
    beta = np.linalg.lstsq(flat, np.concatenate([e.reshape(-1) for e in err]), rcond=None)[0]
    resid = [e - j @ beta for j, e in zip(jac, err, strict=True)]
    return jac, resid, beta


def test_streamed_equals_the_whole_matrix_form() -> None:
    """Up to the products of a run's first and last L samples, left out by design."""
    rng = np.random.default_rng(3)
    jac, resid, _ = _fitted(rng, runs=2, samples=150, n=2, p=6)
    cov, info = _streamed(jac, resid, lag=4, block=1000)
    whole = _whole(jac, resid, lag=4)
    np.testing.assert_allclose(np.diag(cov), np.diag(whole), rtol=2e-3)
    assert info.gamma.shape == (5,) and not info.tapered


@pytest.mark.parametrize("block", [1, 3, 7, 149])
def test_blocks_equal_one_block(block: int) -> None:
    """Block edges inside the 2L tail, at one sample and near the run's end change nothing."""
    rng = np.random.default_rng(4)
    jac, resid, _ = _fitted(rng, runs=2, samples=150, n=2, p=6)
    one, info_one = _streamed(jac, resid, lag=5, block=10_000)
    many, info_many = _streamed(jac, resid, lag=5, block=block)
    np.testing.assert_allclose(many, one, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(info_many.gamma, info_one.gamma, rtol=1e-10)


def test_white_errors_give_the_textbook_covariance() -> None:
    """No lags: the residual variance corrected by rows/(rows − P) times H⁻¹."""
    rng = np.random.default_rng(5)
    jac, resid, _ = _fitted(rng, runs=1, samples=300, n=3, p=8)
    cov, info = _streamed(jac, resid, lag=0, block=50)
    flat = jac[0].reshape(-1, 8)
    rows = flat.shape[0]
    s2 = float(np.sum(resid[0] ** 2)) / (rows - 8)
    np.testing.assert_allclose(cov, s2 * np.linalg.inv(flat.T @ flat), rtol=1e-9)
    np.testing.assert_allclose(info.gamma, [s2], rtol=1e-9)


def test_an_exact_fit_has_no_uncertainty() -> None:
    """Residuals of zero (noise-free data fitted exactly): zero covariance, not an error."""
    rng = np.random.default_rng(6)
    jac, resid, _ = _fitted(rng, runs=2, samples=120, n=2, p=5)
    cov, info = _streamed(jac, [np.zeros_like(e) for e in resid], lag=3, block=40)
    assert np.array_equal(cov, np.zeros_like(cov))
    assert np.array_equal(info.gamma, np.zeros(4)) and info.long_run == 1.0


def test_matches_monte_carlo_where_newey_west_is_short() -> None:
    """Decimated white errors, slow regressors: the σ agree with the Monte Carlo spread.

    The regressors are held fixed and only the errors are drawn again, as in the validation
    study's torque-noise scenarios; the long-run variance of decimated white noise is about
    1.2 times its variance, which the plain estimate ignores and Newey-West only partly sees.
    """
    rng = np.random.default_rng(6)
    samples, n, p, lag = 200, 2, 16, 6
    jac = [_slow_design(rng, samples, n, p) for _ in range(2)]
    flat = np.vstack([j.reshape(-1, p) for j in jac])
    h = flat.T @ flat
    estimates, ours, newey, plain = [], [], [], []
    for _ in range(300):
        err = [_decimated_noise(rng, samples, n) for _ in range(2)]
        beta = np.linalg.solve(h, flat.T @ np.concatenate([e.reshape(-1) for e in err]))
        resid = [e - j @ beta for j, e in zip(jac, err, strict=True)]
        estimates.append(beta)
        ours.append(np.diag(_streamed(jac, resid, lag, block=64)[0]))
        meat = LongRunSum(p, 4)
        for j, e in zip(jac, resid, strict=True):
            meat.add(np.matmul(e[:, None, :], j)[:, 0, :])
            meat.end_run()
        newey.append(np.diag(sandwich(h, meat.meat(), flat.shape[0], p)))
        plain.append(np.diag(_streamed(jac, resid, 0, block=64)[0]))
    true_var = np.var(np.array(estimates), axis=0)

    def ratio(v: list[np.ndarray]) -> float:
        """Mean over parameters of the reported variance over the Monte Carlo one."""
        return float(np.mean(np.mean(v, axis=0) / true_var))

    # 300 draws: each variance ratio has a relative sampling error of about 8 %, the mean
    # over 16 parameters a few %.
    assert 0.92 < ratio(ours) < 1.08
    assert ratio(plain) < 0.88
    assert ratio(newey) < ratio(ours) - 0.05


def test_refuses_bad_input() -> None:
    with pytest.raises(UsageError, match="square"):
        LaggedSums(np.zeros((2, 3)), 1)
    with pytest.raises(UsageError, match="lag"):
        LaggedSums(np.eye(2), -1)
    sums = LaggedSums(np.eye(2), 1)
    with pytest.raises(UsageError, match="expected"):
        sums.add(np.zeros((4, 1, 3)), np.zeros((4, 1)))
    sums.add(np.ones((1, 1, 2)), np.ones((1, 1)))
    sums.end_run()
    with pytest.raises(UsageError, match="more equations"):
        sums.covariance()


@pytest.mark.parametrize(("block", "sub"), [(10_000, 512), (7, 3), (1, 1), (64, 5)])
def test_lagged_grams_equal_the_sums_over_pairs(monkeypatch, block: int, sub: int) -> None:
    """H and D_d = Σ_k (J_kᵀJ_(k+d) + J_(k+d)ᵀJ_k) within each run, as summed pair by pair,
    with runs shorter than the lag and block and sub-block edges inside it."""
    monkeypatch.setattr(autocov, "SUB_BLOCK", sub)
    rng = np.random.default_rng(8)
    lag, n, p = 9, 3, 5
    jac = [_slow_design(rng, k, n, p) + 0.1 * rng.standard_normal((k, n, p)) for k in (150, 4, 37)]
    resid = [rng.standard_normal(j.shape[:2]) for j in jac]
    sums = LaggedSums(np.eye(p), lag)
    for j, e in zip(jac, resid, strict=True):
        for start in range(0, j.shape[0], block):
            sums.add(j[start : start + block], e[start : start + block])
        sums.end_run()
    expected = [sum(np.einsum("kip,kiq->pq", j, j) for j in jac)]
    for d in range(1, lag + 1):
        g = sum(np.einsum("kip,kiq->pq", j[:-d], j[d:]) for j in jac if j.shape[0] > d)
        expected.append(g + g.T)
    scale = np.abs(expected[0]).max()
    assert len(sums.grams) == lag + 1
    for got, want in zip(sums.grams, expected, strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(sums.bread, expected[0], rtol=0, atol=1e-12 * scale)
