"""Entries left out of Case 2 (``Design.row_weight``, ``leaveout.without_rows``,
``leaveout.near_reversals``).

Each product of a design with some entries left out is checked against the same product on
the kept rows of the unweighted design, built by indexing (not through the weight), and the
fit against a least squares solved by numpy on those rows.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from drivegain.errors import UsageError
from drivegain.identify.casenoise import gain_scores
from drivegain.identify.cases import CaseCovariance, case_covariance, fit_case
from drivegain.identify.design import ls_transform, make_design
from drivegain.identify.gains import Estimator, estimate_gains
from drivegain.identify.leaveout import MISFIT_KAPPA, near_reversals, without_rows
from drivegain.identify.mlmodel import Whitening
from drivegain.identify.predict import predictions


def _design(world, run):
    form = world.robot.wrist_friction
    return make_design(run, world.bases[form], form, world.robot)


@pytest.fixture(scope="module")
def pair(world, noisy_run):
    """An unloaded and a loaded run, filtered (they carry reversal shares)."""
    rng = np.random.default_rng(77)
    return tuple(
        _design(world, noisy_run(which, payload, rng, duration=20.0, label=label))
        for which, payload, label in ((0, None, "unloaded"), (1, world.payload, "loaded"))
    )


def _drop(d, seed: int) -> np.ndarray:
    """A different random 30 % of the entries of each joint."""
    return np.random.default_rng(seed).random((d.rows, d.n)) < 0.3


def test_unit_weights_change_nothing(pair) -> None:
    a = pair[1]
    ones = dataclasses.replace(a, row_weight=np.ones((a.rows, a.n)))
    np.testing.assert_array_equal(ones.factors(), a.factors())
    coef = np.random.default_rng(1).standard_normal(a.m)
    np.testing.assert_array_equal(ones.dot(coef), a.dot(coef))
    w = np.random.default_rng(2).standard_normal((a.rows, a.n))
    np.testing.assert_array_equal(ones.tdot(w), a.tdot(w))
    assert ones.entries(3) == a.rows


def test_products_are_those_of_the_kept_rows(pair) -> None:
    a = pair[1]
    drop = _drop(a, 3)
    left = without_rows(a, drop)
    f = left.factors()
    for j in range(a.n):
        kept = a.block(j)[~drop[:, j]]
        np.testing.assert_allclose(f[j].T @ f[j], kept.T @ kept, rtol=1e-9, atol=1e-9)
        np.testing.assert_array_equal(left.block(j)[drop[:, j]], 0.0)
        assert left.entries(j) == int((~drop[:, j]).sum())
    coef = np.random.default_rng(4).standard_normal(a.m)
    np.testing.assert_allclose(left.dot(coef), np.where(drop, 0.0, a.dot(coef)), rtol=1e-12)
    w = np.random.default_rng(5).standard_normal((a.rows, a.n))
    np.testing.assert_allclose(left.tdot(w), a.tdot(np.where(drop, 0.0, w)), rtol=1e-12)
    # a subset keeps its rows' weights; leaving out more multiplies
    sl = slice(10, 60)
    np.testing.assert_array_equal(left.subset(sl).row_weight, left.row_weight[sl])
    both = without_rows(left, _drop(a, 6))
    np.testing.assert_array_equal(both.row_weight, (~drop & ~_drop(a, 6)).astype(float))
    with pytest.raises(ValueError, match="drop must be"):
        without_rows(a, drop[:-1])


def test_case2_on_the_kept_rows_is_their_least_squares(world, pair) -> None:
    gains = np.asarray(world.truth.gains, dtype=float)
    names = list(world.bases[world.robot.wrist_friction].names)
    drops = [_drop(d, 10 + k) for k, d in enumerate(pair)]
    left = [without_rows(d, m) for d, m in zip(pair, drops, strict=True)]
    fit = fit_case("kept", left, gains, names, covariance=False)
    transforms = [ls_transform(pair[0], None, 1, gains), ls_transform(pair[1], 0, 1, gains)]
    p = transforms[0].shape[1] - 1
    # σ_j from joint j's own OLS on its kept rows, dof = kept rows − rank
    sigma = np.empty(pair[0].n)
    for j in range(pair[0].n):
        rows = np.vstack(
            [d.block(j)[~m[:, j]] @ t for d, m, t in zip(pair, drops, transforms, strict=True)]
        )
        x_j, *_ = np.linalg.lstsq(rows[:, :p], rows[:, p], rcond=1e-10)
        rank = np.linalg.matrix_rank(rows[:, :p])
        sigma[j] = np.linalg.norm(rows[:, :p] @ x_j - rows[:, p]) / np.sqrt(rows.shape[0] - rank)
    np.testing.assert_allclose(fit.sigma_joint, sigma, rtol=1e-6)
    a_rows, y_rows = [], []
    for d, m, t in zip(pair, drops, transforms, strict=True):
        for j in range(d.n):
            kept = d.block(j)[~m[:, j]] @ t / sigma[j]
            a_rows.append(kept[:, :p])
            y_rows.append(kept[:, p])
    x, *_ = np.linalg.lstsq(np.vstack(a_rows), np.concatenate(y_rows), rcond=None)
    np.testing.assert_allclose(fit.payloads[0].values, x[-10:], rtol=1e-6)
    assert fit.rows == sum(int((~m).sum()) for m in drops)


def test_near_reversals_follows_the_drives_a_joint_carries(pair) -> None:
    a = pair[0]
    n = a.n
    share = np.zeros((a.rows, n))
    share[50, 0] = 0.5  # drive 1 at sample 50
    share[80, n - 1] = -0.2  # the last drive (the coupled wrist's) at sample 80, signed
    share[90, 1] = 0.05  # at the limit: not near
    d = dataclasses.replace(a, run=dataclasses.replace(a.run, reversal_share=share))
    near = near_reversals(d, margin=0)
    coupled = np.flatnonzero(a.kt[:, n - 1] != 0.0)  # the joints whose torque drive n carries
    assert coupled.size >= 2  # the TX-40's wrist: joints 5 and 6
    expected = np.zeros((a.rows, n), dtype=bool)
    expected[50, 0] = True
    expected[80, coupled] = True
    np.testing.assert_array_equal(near, expected)
    wide = near_reversals(d, margin=2)
    np.testing.assert_array_equal(np.flatnonzero(wide[:, 0]), np.arange(48, 53))
    assert not near_reversals(d, limit=0.6).any()
    none = dataclasses.replace(a, run=dataclasses.replace(a.run, reversal_share=None))
    assert not near_reversals(none).any()
    with pytest.raises(ValueError, match="limit"):
        near_reversals(d, limit=1.0)
    with pytest.raises(ValueError, match="margin"):
        near_reversals(d, margin=-1)
    # only the drives asked for: without drive 1, sample 50 is not near
    drives = np.ones(n, dtype=bool)
    drives[0] = False
    expected[50, 0] = False
    np.testing.assert_array_equal(near_reversals(d, margin=0, drives=drives), expected)
    with pytest.raises(ValueError, match="drives must be"):
        near_reversals(d, drives=drives[:-1])


def test_case2_leaves_out_the_reversals_the_error_model_finds_misfit(world, pair) -> None:
    """The gate on the gains' κ̂: below it Case 2 is the error model's on every entry; at it
    the entries near those drives' reversals are left out and σ is Newey-West's."""
    a, b = pair
    res = estimate_gains(a, b, world.payload, world.robot.apriori_gains, estimator=Estimator.ML)
    # the covariance the estimate reports leaves out the reversal Coulomb coefficients that
    # the fit's θ holds before the gains: its gains' block ends at the payload's columns
    nb = res.covariance.shape[0] - a.n - res.payload_unknown.size
    cov = res.covariance[nb : nb + a.n, nb : nb + a.n]
    names = list(world.bases[world.robot.wrist_friction].names)

    def with_kappa(kappa: np.ndarray):
        w = res.noise.whitening
        return dataclasses.replace(res.noise, whitening=Whitening(w.noise, kappa))

    def case2(noise, **kw):
        return fit_case("case2", [a, b], res.gains, names, gain_cov=cov, noise=noise, **kw)

    quiet = with_kappa(np.full(a.n, 0.99 * MISFIT_KAPPA))
    kept = case2(quiet)
    every = case2(quiet, leave_out_misfit=False)
    assert (kept.left_out, kept.covariance) == (0, CaseCovariance.ERROR_MODEL)
    np.testing.assert_array_equal(kept.payloads[0].std, every.payloads[0].std)

    kappa = np.zeros(a.n)
    kappa[[0, a.n - 1]] = MISFIT_KAPPA  # drive 1 and the coupled wrist's
    drives = kappa >= MISFIT_KAPPA
    drops = [near_reversals(d, drives=drives) for d in (a, b)]
    assert 0 < sum(int(x.sum()) for x in drops) < sum(x.size for x in drops)
    fit = case2(with_kappa(kappa))
    assert fit.covariance == CaseCovariance.NEWEY_WEST_KEPT
    assert fit.left_out == sum(int(x.sum()) for x in drops)
    # the fit of the kept entries, its σ Newey-West's with the gains' covariance and their
    # lagged correlation with this fit's residuals (gain_scores of the gains' every entry)
    left = [without_rows(d, x) for d, x in zip((a, b), drops, strict=True)]
    ref = fit_case("case2", left, res.gains, names, gain_cov=cov)
    np.testing.assert_allclose(fit.payloads[0].values, ref.payloads[0].values, rtol=1e-12)
    noise = with_kappa(kappa)
    scores = [gain_scores(noise, d) for d in left]
    transforms = [ls_transform(left[0], None, 1, res.gains), ls_transform(left[1], 0, 1, res.gains)]
    joint, _ = case_covariance(
        left, transforms, ref.sigma_joint, ref.wls.x, cov, gain_scores=scores
    )
    np.testing.assert_allclose(fit.payloads[0].std, np.sqrt(np.diag(joint)[a.nb :]), rtol=1e-12)
    # the correlation is not nothing: the known mass, which the gains reproduce, loses most
    # of the σ independence gives it
    known = world.payload.known_mask()
    assert np.all(fit.payloads[0].std[known] < 0.5 * ref.payloads[0].std[known])
    assert fit.rows == ref.rows < every.rows
    # the error norms count every entry, computed here from the torques themselves
    measured, computed = zip(
        *predictions([a, b], res.gains, fit.base, [fit.payloads[0].values]), strict=True
    )
    rho = np.linalg.norm(np.concatenate(measured) - np.concatenate(computed))
    np.testing.assert_allclose(fit.residual_norm, rho, rtol=1e-9)
    assert fit.residual_norm != ref.residual_norm
    with pytest.raises(UsageError, match="gain_cov"):  # refused whether or not entries go
        fit_case("case2", [a, b], res.gains, names, noise=with_kappa(kappa))
