"""Passes over row blocks equal the whole-matrix passes they replace (issue 19: bounded memory).

Each block-wise computation is checked against a direct whole-matrix version written here, on
random data and on a short simulated pair of runs, with block sizes that put block edges
inside the HAC lag, at a single sample, and beyond the run.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.stats import chi2

from drivegain.identify import cases, design, mlmodel
from drivegain.identify.autocov import LaggedSums
from drivegain.identify.crossval import split_factors, split_runs
from drivegain.identify.design import ls_transform, make_design
from drivegain.identify.eiv import eiv_test
from drivegain.identify.hac import (
    LongRunSum,
    bartlett_lag,
    long_run_covariance,
    phase_bins,
    sandwich,
    with_repeats,
)
from drivegain.identify.ml import ml_fit
from drivegain.identify.mlmodel import Whitening, ls_rows, run_pair, whitened_block
from drivegain.identify.mlstart import least_squares
from drivegain.identify.prepare import _compact
from drivegain.identify.weighting import joint_sigma

RTOL = 1e-9


def _meat_by_lags(scores: list[np.ndarray], lag: int) -> np.ndarray:
    """Newey-West meat summed lag by lag over whole runs (the textbook form)."""
    p = scores[0].shape[1]
    meat = np.zeros((p, p))
    for s in scores:
        meat += s.T @ s
        for lg in range(1, min(lag, s.shape[0] - 1) + 1):
            gam = s[lg:].T @ s[:-lg]
            meat += (1.0 - lg / (lag + 1.0)) * (gam + gam.T)
    return meat


def _ar_series(rng: np.random.Generator, n: int, p: int, rho: float) -> np.ndarray:
    e = rng.standard_normal((n, p))
    x = np.empty_like(e)
    x[0] = e[0]
    for k in range(1, n):
        x[k] = rho * x[k - 1] + e[k]
    return x - x.mean(axis=0)


@pytest.mark.parametrize("lag", [0, 1, 7, 64, 500])
def test_long_run_sum_in_blocks_equals_the_sum_over_lags(lag: int) -> None:
    rng = np.random.default_rng(lag)
    runs = [_ar_series(rng, n, 4, 0.8) for n in (400, 123, 3)]  # the last shorter than lags
    ref = _meat_by_lags(runs, lag)
    scale = np.abs(ref).max()
    np.testing.assert_allclose(long_run_covariance(runs, lag), ref, rtol=0, atol=1e-12 * scale)
    for block in (1, 5, 64, 65, 1000):  # edges inside the lag, at it, beyond the run
        acc = LongRunSum(4, lag)
        for s in runs:
            for k in range(0, s.shape[0], block):
                acc.add(s[k : k + block])
            acc.end_run()
        np.testing.assert_allclose(acc.meat(), ref, rtol=0, atol=1e-12 * scale)


def test_uneven_blocks_and_empty_ones_change_nothing() -> None:
    rng = np.random.default_rng(5)
    s = _ar_series(rng, 300, 3, 0.5)
    acc = LongRunSum(3, 9)
    edges = [0, 0, 4, 5, 40, 41, 200, 300]
    for lo, hi in itertools.pairwise(edges):
        acc.add(s[lo:hi])
    acc.end_run()
    ref = _meat_by_lags([s], 9)
    np.testing.assert_allclose(acc.meat(), ref, rtol=0, atol=1e-12 * np.abs(ref).max())


@pytest.fixture(scope="module")
def pair(world, noisy_run):
    rng = np.random.default_rng(19)
    bp = world.bases[world.robot.wrist_friction]
    runs = [
        noisy_run(0, None, rng, duration=12.0, label="unloaded"),
        noisy_run(1, world.payload, rng, duration=12.0, label="loaded"),
    ]
    return [make_design(r, bp, world.robot.wrist_friction, world.robot) for r in runs]


def _whole_least_squares(runs, kt):
    """The least squares with V as regressor on whole stacked matrices (lstsq twice)."""
    n = runs[0].v.shape[1]
    mats = [ls_rows(r, kt) for r in runs]
    p = mats[0].shape[2]

    def system(w):
        a = np.vstack([(m * w[None, :, None]).reshape(-1, p) for m in mats])
        y = np.concatenate([(r.tau_known * w[None, :]).reshape(-1) for r in runs])
        return a, y

    w = np.ones(n)
    a, y = system(w)
    theta = np.linalg.lstsq(a, y, rcond=None)[0]
    sigma = np.sqrt(np.mean(((a @ theta - y).reshape(-1, n)) ** 2, axis=0))
    w = 1.0 / np.maximum(sigma, 1e-9 * sigma.max())
    a, y = system(w)
    theta = np.linalg.lstsq(a, y, rcond=None)[0]
    return theta, w, a.T @ a


@pytest.mark.parametrize("chunk", [37, 500, 100_000])
def test_block_least_squares_equals_the_whole_matrix_one(world, pair, monkeypatch, chunk) -> None:
    monkeypatch.setattr(mlmodel, "CHUNK", chunk)
    runs = run_pair(*pair, world.payload)
    kt = np.asarray(pair[0].kt, float)
    theta, w, hessian = _whole_least_squares(runs, kt)
    ls = least_squares(runs, kt)
    np.testing.assert_allclose(ls.theta, theta, rtol=RTOL, atol=1e-12 * np.abs(theta).max())
    np.testing.assert_allclose(ls.weights, w, rtol=RTOL)
    np.testing.assert_allclose(ls.hessian, hessian, rtol=0, atol=1e-12 * np.abs(hessian).max())


def test_ml_fit_and_eiv_test_do_not_depend_on_the_block_size(world, pair, monkeypatch) -> None:
    a, b = pair
    outs = []
    for chunk in (2048, 53):
        monkeypatch.setattr(mlmodel, "CHUNK", chunk)
        fit = ml_fit(a, b, world.payload)
        outs.append((fit, eiv_test(fit, a, b, world.payload)))
    (f1, t1), (f2, t2) = outs
    # Sums in another order differ by round-off, and the search stops when a step moves the fit
    # by less than 1e-5 σ (ml.DECREMENT_TOL): a difference at that threshold may cost one more
    # step. Anything the block size changed in earnest would show far above these bounds.
    assert f1.lag == f2.lag and abs(f1.iterations - f2.iterations) <= 1
    np.testing.assert_allclose(f2.gains, f1.gains, rtol=0, atol=1e-4 * f1.gain_std.min())
    np.testing.assert_allclose(f2.gain_std, f1.gain_std, rtol=1e-6)
    # each entry against its own scale √(C_ii C_jj): small off-diagonal terms carry the
    # round-off of the large ones
    scale = np.outer(f1.std_all, f1.std_all)
    np.testing.assert_allclose(f2.covariance / scale, f1.covariance / scale, rtol=0, atol=1e-6)
    # a difference of two nearly equal estimates over its own σ: the bound above, in σ units
    np.testing.assert_allclose(t2.statistic, t1.statistic, rtol=1e-4)
    np.testing.assert_allclose(t2.ls_std, t1.ls_std, rtol=RTOL)
    np.testing.assert_allclose(t2.difference_std, t1.difference_std, rtol=1e-6)


def test_eiv_test_equals_its_whole_matrix_form(world, pair) -> None:
    """The test's statistic from whole per-sample influence matrices, as first written."""
    a, b = pair
    fit = ml_fit(a, b, world.payload)
    test = eiv_test(fit, a, b, world.payload)
    runs = run_pair(*pair, world.payload)
    kt = np.asarray(a.kt, float)
    theta_ls, w, bread_ls = _whole_least_squares(runs, kt)
    mats = [ls_rows(r, kt) for r in runs]
    h_ls = np.linalg.pinv(bread_ls, hermitian=True)
    infl_ls = [
        -np.matmul(((m @ theta_ls - r.tau_known) * w**2)[:, None, :], m)[:, 0, :] @ h_ls
        for m, r in zip(mats, runs, strict=True)
    ]
    theta = fit.theta
    whiten = Whitening(fit.noise, fit.kappa)
    blocks = [whitened_block(theta, r, np.linalg.inv(kt), whiten) for r in runs]
    bread = sum(jw.reshape(-1, theta.size).T @ jw.reshape(-1, theta.size) for jw, _ in blocks)
    h_ml = np.linalg.pinv(bread, hermitian=True)
    infl_ml = [np.matmul(ew[:, None, :], jw)[:, 0, :] @ h_ml for jw, ew in blocks]
    g = slice(fit.nb, fit.nb + a.n)
    cov_d = _meat_by_lags([(x - y)[:, g] for x, y in zip(infl_ls, infl_ml, strict=True)], fit.lag)
    d = theta_ls[g] - fit.gains
    stat = float(d @ np.linalg.solve(cov_d, d))
    np.testing.assert_allclose(test.statistic, stat, rtol=1e-8)
    np.testing.assert_allclose(test.p_value, chi2.sf(stat, a.n), rtol=1e-6, atol=1e-300)
    np.testing.assert_allclose(test.ls_gains, theta_ls[g], rtol=RTOL)
    ls_cov = _meat_by_lags([x[:, g] for x in infl_ls], fit.lag)
    np.testing.assert_allclose(test.ls_std, np.sqrt(np.diag(ls_cov)), rtol=RTOL)
    # and the fit's own covariance is the one of each run's whole arrays in one block
    sums = LaggedSums(h_ml, fit.lag)
    for jw, ew in blocks:
        sums.add(jw, ew)
        sums.end_run()
    cov = sums.covariance()[0]
    np.testing.assert_allclose(fit.gain_std, np.sqrt(np.diag(cov))[g], rtol=RTOL)


@pytest.mark.parametrize("block", [29, 4096])
def test_case_covariance_in_blocks_equals_the_whole_matrix_one(world, pair, monkeypatch, block):
    designs = list(pair)
    gains = world.truth.gains
    factors = [d.factors() for d in designs]
    transforms = [ls_transform(d, s, 1, gains) for d, s in zip(designs, (None, 0), strict=True)]
    sigma = joint_sigma(designs, factors, transforms)
    x = cases.fit_case("given", designs, gains, [f"p{i}" for i in range(designs[0].nb)]).wls.x
    gain_cov = np.diag((1e-3 * gains) ** 2)
    monkeypatch.setattr(cases, "ROW_BLOCK", block)
    cov, lag = cases.case_covariance(designs, transforms, sigma, x, gain_cov)
    # the whole-matrix form
    p, n = x.size, designs[0].n
    x_aug = np.append(x, -1.0)
    bread, cross = np.zeros((p, p)), np.zeros((p, n))
    scores, resid = [], []
    for d, t in zip(designs, transforms, strict=True):
        blk = np.stack([(d.block(j) @ t) / sigma[j] for j in range(n)], axis=1)
        a_, e = blk[:, :, :p], blk @ x_aug
        flat = a_.reshape(-1, p)
        bread += flat.T @ flat
        scores.append(np.matmul(e[:, None, :], a_)[:, 0, :])
        resid.append(e)
        dc = d.run.current[:, None, :] * d.kt[None, :, :] / sigma[None, :, None]
        cross += flat.T @ dc.reshape(-1, n)
    assert lag == bartlett_lag(resid)
    rows = sum(d.rows for d in designs) * n
    ref = sandwich(bread, _meat_by_lags(scores, lag), rows, p)
    # each run's whole score matrix summed by phase (the runs know their period)
    folded = []
    for d, sc in zip(designs, scores, strict=True):
        phases = phase_bins(d.run.t, d.run.period_s, d.run.rate_hz, d.run.phase_origin_s)
        assert phases is not None
        folded.append(np.zeros((phases[1], p)))
        np.add.at(folded[-1], phases[0], sc)
    ref = with_repeats(ref, bread, folded, lag, rows)[0]
    j_g = np.linalg.pinv(bread, hermitian=True) @ cross
    ref = ref + j_g @ gain_cov @ j_g.T
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(ref)), rtol=RTOL)


def test_compacting_in_place_equals_gathering() -> None:
    rng = np.random.default_rng(4)
    a = rng.standard_normal((10_000, 2, 3))
    keep = np.flatnonzero(rng.random(10_000) < 0.7)
    expected = a[keep]
    np.testing.assert_array_equal(_compact(a, keep), expected)


def test_split_factors_give_each_runs_whole_factor(pair) -> None:
    whole, fitted = split_factors(pair, 0.3)
    train, _ = split_runs(pair, 0.3)
    for d, w, f, t in zip(pair, whole, fitted, train, strict=True):
        direct = d.factors()
        for j in range(d.n):  # R is unique up to the signs of its rows: compare RᵀR = AᵀA
            gram = direct[j].T @ direct[j]
            np.testing.assert_allclose(w[j].T @ w[j], gram, rtol=0, atol=1e-12 * np.abs(gram).max())
        np.testing.assert_array_equal(f, t.factors())


def test_a_fit_without_covariance_has_the_same_estimate(world, pair) -> None:
    names = [f"p{i}" for i in range(pair[0].nb)]
    full = cases.fit_case("x", pair, world.truth.gains, names)
    bare = cases.fit_case("x", pair, world.truth.gains, names, covariance=False)
    np.testing.assert_array_equal(bare.wls.x, full.wls.x)
    assert bare.relative_error == full.relative_error
    assert np.isnan(bare.base_std).all() and bare.lag == 0


@pytest.mark.parametrize("block", [37, 4096])
def test_factors_of_the_nonzero_columns_are_those_of_the_whole_block(pair, monkeypatch, block):
    """R_j of the columns of D_j that may be non-zero, in row blocks: R_jᵀR_j = D_jᵀD_j, and
    upper triangular (the unloaded run's payload columns, the other joints' currents and the
    links before joint j are left out)."""
    monkeypatch.setattr(design, "FACTOR_BLOCK", block)
    for d in pair:
        factors = d.factors()
        assert factors.shape == (d.n, d.m, d.m)
        for j in range(d.n):
            whole = d.block(j)
            gram = whole.T @ whole
            np.testing.assert_array_equal(np.triu(factors[j]), factors[j])
            np.testing.assert_allclose(
                factors[j].T @ factors[j], gram, rtol=0, atol=1e-12 * np.abs(gram).max()
            )


def test_design_products_equal_those_of_its_blocks(pair) -> None:
    """D_j c for every joint, and Σ_j w_kj D_j,k for every sample, without building D_j."""
    rng = np.random.default_rng(5)
    for d in pair:
        coef = rng.standard_normal(d.m)
        w = rng.standard_normal((d.rows, d.n))
        by_joint = d.dot(coef)
        weighted = d.tdot(w)
        expected = sum(w[:, j : j + 1] * d.block(j) for j in range(d.n))
        for j in range(d.n):
            want = d.block(j) @ coef
            np.testing.assert_allclose(
                by_joint[:, j], want, rtol=0, atol=1e-12 * np.abs(want).max()
            )
        np.testing.assert_allclose(weighted, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_long_run_sums_merge_as_if_summed_together() -> None:
    rng = np.random.default_rng(6)
    runs = [_ar_series(rng, n, 3, 0.7) for n in (200, 50)]
    together, first, second = LongRunSum(3, 8), LongRunSum(3, 8), LongRunSum(3, 8)
    for s in runs:
        together.add(s)
        together.end_run()
    first.add(runs[0])
    first.end_run()
    second.add(runs[1])
    second.end_run()
    first.merge(second)
    np.testing.assert_allclose(first.meat(), together.meat(), rtol=1e-13)


def test_eiv_sums_of_the_covariance_pass_equal_the_tests_own_pass(world, pair) -> None:
    """ml_fit(influence=True) sums the test's scores with its covariance (runs in blocks, maybe
    in a child); the test from them equals the test's own pass over the samples."""
    a, b = pair
    fit = ml_fit(a, b, world.payload, influence=True)
    assert fit.linear is not None and fit.influence is not None
    runs = run_pair(*pair, world.payload)
    kt = np.asarray(a.kt, float)
    own = eiv_test(fit, a, b, world.payload, ls=least_squares(runs, kt))  # not fit.linear
    fused = eiv_test(fit, a, b, world.payload)
    np.testing.assert_array_equal(fused.ls_gains, own.ls_gains)
    np.testing.assert_allclose(fused.statistic, own.statistic, rtol=1e-10)
    np.testing.assert_allclose(fused.ls_std, own.ls_std, rtol=1e-10)
    np.testing.assert_allclose(fused.difference_std, own.difference_std, rtol=1e-10)
    # and the fit itself is the one without the test's sums
    plain = ml_fit(a, b, world.payload)
    np.testing.assert_array_equal(plain.gains, fit.gains)
    np.testing.assert_array_equal(plain.covariance, fit.covariance)


def test_another_forms_factors_reuse_the_joints_it_does_not_change(world, pair) -> None:
    form = world.robot.wrist_friction
    other = next(f for f in world.bases if f is not form)
    od = [make_design(d.run, world.bases[other], other, world.robot) for d in pair]
    same = [[d.same_rows(m, j) for j in range(d.n)] for d, m in zip(od, pair, strict=True)]
    assert all(any(s) and not all(s) for s in same)  # only the coupled joints' rows differ
    whole, fitted = split_factors(pair, 0.3)
    own = split_factors(od, 0.3)
    reused = split_factors(od, 0.3, like=(pair, whole, fitted))
    for a, b in zip(own[0] + own[1], reused[0] + reused[1], strict=True):
        np.testing.assert_array_equal(a, b)  # bit for bit
    assert not pair[0].same_rows(pair[1], 0)  # another run's rows are never the same
