"""Case 2's covariance under the gains' error model (identify/casenoise.py).

Checked three ways, each against something computed otherwise: the streamed Toeplitz sum
against the whole-matrix product, the fit's share against a Monte Carlo of the least squares'
linear response to current errors drawn from the model (with correlated drives, reversal
scaling and a lag-1 autocovariance, so a wrong factor shows), and the gains' share against the
maximum-likelihood fit's own covariance, which :mod:`~drivegain.identify.autocov` computes by
other means.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from drivegain.errors import UsageError
from drivegain.identify.casenoise import ToeplitzSum, case_noise, gain_scores, model_sums
from drivegain.identify.cases import CaseCovariance, case_covariance, fit_case
from drivegain.identify.design import ls_transform, make_design
from drivegain.identify.gains import Estimator, estimate_gains
from drivegain.identify.hac import matched_root
from drivegain.identify.leaveout import near_reversals, without_rows
from drivegain.identify.mlmodel import Whitening, reversal_of

RATE = 250.0
DURATION = 24.0


def _design(world, run):
    return make_design(
        run, world.bases[world.robot.wrist_friction], world.robot.wrist_friction, world.robot
    )


@pytest.fixture(scope="module")
def noisy_pair(world, noisy_run):
    """Designs of an unloaded and a loaded run with 1 % of rated current noise on every drive."""
    rated = np.array([j.rated_current for j in world.robot.joints])
    rng = np.random.default_rng(2024)
    return tuple(
        _design(
            world,
            noisy_run(
                which,
                payload,
                rng,
                duration=DURATION,
                rate=RATE,
                torque_noise=0.0,
                current_noise=0.01 * rated,
                label=label,
            ),
        )
        for which, payload, label in ((0, None, "unloaded"), (1, world.payload, "loaded"))
    )


def _gain_block(res) -> np.ndarray:
    """The gains' covariance of the maximum-likelihood fit before its repeat factor: the one
    its error model gives, so that the model's sums cancel it exactly where they should."""
    fit = res.ml
    g = slice(fit.nb, fit.nb + res.gains.size)
    scale = np.ones(fit.theta.size) if fit.repeat_scale is None else fit.repeat_scale
    return np.asarray(fit.covariance[g, g] / np.outer(scale[g], scale[g]))


def case_covariance_of(fit, designs, gain_cov, noise=None, gain_scores=None) -> np.ndarray:
    """:func:`case_covariance` of a Case 2 fit of ``designs`` (a loaded second run), unclipped."""
    a, b = designs
    transforms = [ls_transform(a, None, 1, fit.gains), ls_transform(b, 0, 1, fit.gains)]
    return case_covariance(
        designs,
        transforms,
        fit.sigma_joint,
        fit.wls.x,
        gain_cov,
        noise=noise,
        gain_scores=gain_scores,
    )[0]


def test_toeplitz_sum_matches_the_whole_matrix_product() -> None:
    rng = np.random.default_rng(5)
    gamma = np.array([1.0, 0.4, -0.2, 0.05])
    n, w = 3, 4
    runs = [rng.standard_normal((29, n, w)), rng.standard_normal((11, n, w))]
    expected = np.zeros((w, w))
    for f in runs:
        size = f.shape[0]
        lags = np.abs(np.arange(size)[:, None] - np.arange(size)[None, :])
        toeplitz = np.where(lags < gamma.size, gamma[np.minimum(lags, gamma.size - 1)], 0.0)
        flat = f.reshape(size * n, w)
        expected += flat.T @ np.kron(toeplitz, np.eye(n)) @ flat
    for cuts in ([29], [7, 1, 2, 19], [1] * 29):  # blocks shorter than the lag too
        acc = ToeplitzSum(gamma, w)
        for f, sizes in zip(runs, (cuts, [5, 6]), strict=True):
            at = 0
            for size in sizes:
                acc.add(f[at : at + size])
                at += size
            acc.end_run()
        np.testing.assert_allclose(acc.total(), expected, rtol=1e-12, atol=1e-12)


def test_toeplitz_sum_refuses_bad_shapes() -> None:
    with pytest.raises(UsageError, match="gamma"):
        ToeplitzSum(np.empty(0), 2)
    with pytest.raises(UsageError, match="expected"):
        ToeplitzSum(np.ones(2), 2).add(np.ones((4, 3)))


@pytest.mark.parametrize("left_out", [False, True], ids=["all-rows", "near-reversals-left-out"])
def test_fit_share_matches_a_monte_carlo_of_the_least_squares(
    world, noisy_pair, left_out: bool
) -> None:
    """Draw current errors from the model, push them through the weighted least squares of
    Case 2 (its rows and right-hand side built by the design, not by the module) and compare
    the spread of the estimates with H⁻¹ Σ Uᵀγ U H⁻¹; also with the entries near reversals
    left out, whose errors then reach no estimate."""
    a, b = noisy_pair
    assert reversal_of(a) is not None  # the S_k factor must be exercised
    if left_out:
        a, b = (without_rows(d, near_reversals(d)) for d in (a, b))
        assert 0 < a.entries(0) < a.rows
    n = a.n
    gains = np.asarray(world.truth.gains, float)
    # Correlated drives and a strong reversal variance: a transposed or missing factor shows.
    root = np.tril(np.full((n, n), 0.3)) + np.diag(np.linspace(0.5, 1.0, n))
    noise_cov = root @ root.T * 1e-4
    kappa = np.full(n, 3.0)
    gamma = np.array([1.0, 0.3])
    model = case_noise(gains, 0, a.kt, Whitening(noise_cov, kappa), gamma, np.eye(n), runs=())
    designs = [a, b]
    transforms = [ls_transform(a, None, 1, gains), ls_transform(b, 0, 1, gains)]
    p = transforms[0].shape[1] - 1
    sigma = np.linspace(0.5, 2.0, n)
    rows = [[slice(k, min(k + 64, d.rows)) for k in range(0, d.rows, 64)] for d in designs]
    s_uu, _, _ = model_sums(designs, transforms, sigma, p, model, rows)
    # The least squares' linear map from the weighted right-hand side to x.
    blocks = [
        np.stack([d.block(j) @ t[:, :p] / sigma[j] for j in range(n)], axis=1)
        for d, t in zip(designs, transforms, strict=True)
    ]
    a_all = np.concatenate([blk.reshape(-1, p) for blk in blocks])
    h_inv = np.linalg.inv(a_all.T @ a_all)
    predicted = h_inv @ s_uu @ h_inv
    rng = np.random.default_rng(11)
    chol = np.linalg.cholesky(noise_cov)
    # MA(1) with γ_0 = 1, γ_1 = 0.3: e_k = c0 z_k + c1 z_(k−1)
    c0, c1 = (np.sqrt(1.6) + np.sqrt(0.4)) / 2, (np.sqrt(1.6) - np.sqrt(0.4)) / 2
    draws = []
    for _ in range(2000):
        rhs = []
        for d in designs:
            z = rng.standard_normal((d.rows + 1, n))
            white = c0 * z[1:] + c1 * z[:-1]
            rev = reversal_of(d)
            scale = np.ones((d.rows, n)) if rev is None else np.sqrt(1.0 + kappa * rev)
            dv = scale * (white @ chol.T)
            torque = dataclasses.replace(d, run=dataclasses.replace(d.run, current=dv)).torque(
                gains
            )
            rhs.append((torque / sigma).reshape(-1))
        draws.append(h_inv @ (a_all.T @ np.concatenate(rhs)))
    empirical = np.cov(np.array(draws).T)
    ratio = np.diag(empirical) / np.diag(predicted)
    # 2000 draws: each variance within about ±3 % (1σ); the mean of ~60 of them much closer.
    assert abs(float(np.mean(ratio)) - 1.0) < 0.03, ratio
    assert np.all(np.abs(ratio - 1.0) < 0.15), ratio


def test_gains_share_is_the_ml_fits_own_covariance(world, noisy_pair) -> None:
    a, b = noisy_pair
    res = estimate_gains(a, b, world.payload, world.robot.apriori_gains, estimator=Estimator.ML)
    fit, noise = res.ml, res.noise
    assert fit is not None and noise is not None
    n = a.n
    transforms = [np.eye(a.m), np.eye(b.m)]
    rows = [[slice(0, a.rows)], [slice(k, min(k + 50, b.rows)) for k in range(0, b.rows, 50)]]
    _, _, s_vv = model_sums([a, b], transforms, np.ones(n), 3, noise, rows)
    g = slice(fit.nb, fit.nb + n)
    scale = np.ones(fit.theta.size) if fit.repeat_scale is None else fit.repeat_scale
    before_repeats = fit.covariance[g, g] / np.outer(scale[g], scale[g])
    np.testing.assert_allclose(s_vv, before_repeats, rtol=1e-8)


def test_case2_under_the_model_and_its_refusals(world, noisy_pair) -> None:
    a, b = noisy_pair
    res = estimate_gains(a, b, world.payload, world.robot.apriori_gains, estimator=Estimator.ML)
    cov = _gain_block(res)
    names = list(world.bases[world.robot.wrist_friction].names)
    plain = fit_case("case2", [a, b], res.gains, names, gain_cov=cov)
    # every entry: this fixture's κ̂ reaches the misfit gate on drives 4 and 6 (1.1-2.4)
    model = fit_case(
        "case2", [a, b], res.gains, names, gain_cov=cov, noise=res.noise, leave_out_misfit=False
    )
    # the same estimate, another covariance of the same size
    np.testing.assert_array_equal(model.base, plain.base)
    assert model.lag == res.noise.lag
    assert (model.covariance, plain.covariance) == (
        CaseCovariance.ERROR_MODEL,
        CaseCovariance.NEWEY_WEST_GAINS,
    )
    known = world.payload.known_mask()
    ratio = model.payloads[0].std / plain.payloads[0].std
    assert np.all((ratio[~known] > 0.5) & (ratio[~known] < 2.0)), ratio
    # The gains were scaled to reproduce the known mass: with their error and the fit's
    # taken together, most of its Case 2 error goes (not all: Case 2 weights the rows
    # otherwise than the gains' fit, so the two errors are not exactly opposite). Its variance
    # comes out positive, not clipped: 0.107 of the plain σ on this fixture.
    var_known = np.diag(case_covariance_of(model, [a, b], cov, res.noise))[a.nb :][known]
    assert np.all(var_known > 0.0), var_known
    assert np.all(model.payloads[0].std[known] < 0.2 * plain.payloads[0].std[known]), ratio
    with pytest.raises(UsageError, match="gain_cov"):
        case_covariance(
            [a], [ls_transform(a, None, 0, res.gains)], np.ones(a.n), np.ones(3), noise=res.noise
        )


def test_newey_west_with_the_gains_scores_finds_the_models_correlation(world, noisy_pair) -> None:
    """The gains' share of each sample (``gain_scores``) lagged against Case 2's own scores
    gives Newey-West the correlation of the two errors that the error model computes from γ:
    the known mass, which the gains were scaled to reproduce, loses most of its σ as under
    the model, and the other parameters' σ agree with the model's."""
    a, b = noisy_pair
    res = estimate_gains(a, b, world.payload, world.robot.apriori_gains, estimator=Estimator.ML)
    cov_g = _gain_block(res)
    names = list(world.bases[world.robot.wrist_friction].names)
    model = fit_case(
        "case2", [a, b], res.gains, names, gain_cov=cov_g, noise=res.noise, leave_out_misfit=False
    )
    scores = [gain_scores(res.noise, d) for d in (a, b)]
    assert all(
        s is not None and s.shape == (d.rows, a.n) for s, d in zip(scores, (a, b), strict=True)
    )
    # to first order the gains' scores sum to zero at the fit (its gradient)
    total = np.sum([s.sum(axis=0) for s in scores], axis=0)
    assert np.all(np.abs(total) < 1e-6 * np.sqrt(np.diag(cov_g)) * a.rows), total
    plain = case_covariance_of(model, [a, b], cov_g)
    joint = case_covariance_of(model, [a, b], cov_g, gain_scores=scores)
    nb = a.nb
    known = world.payload.known_mask()
    std = {k: np.sqrt(np.diag(c))[nb:] for k, c in (("plain", plain), ("joint", joint))}
    # the known mass: the cross term takes away what independence would add
    assert np.all(np.diag(joint)[nb:] > 0.0)
    # The known mass keeps 0.107 of its σ under the model; Newey-West, whose lagged products
    # come out a few % from the model's γ, leaves 0.148 of it on this fixture (1 without the
    # correlation): a small difference of large terms.
    assert np.all(std["joint"][known] < 0.3 * std["plain"][known]), (std, known)
    # the other nine: within 8 % of the model's σ on this fixture
    ratio = std["joint"][~known] / model.payloads[0].std[~known]
    assert np.all((ratio > 0.85) & (ratio < 1.15)), ratio
    with pytest.raises(UsageError, match="scores"):
        case_covariance_of(model, [a, b], None, gain_scores=scores)
    for wrong in (scores[:1], [scores[0], scores[1][:-1]]):
        with pytest.raises(UsageError, match="per design"):
            case_covariance_of(model, [a, b], cov_g, gain_scores=wrong)
    # Gains far more certain than their scores say (a covariance from another model): the
    # correlation is taken at that size, and the covariance stays positive semidefinite.
    for factor in (1e-6, 1e3):
        cov = case_covariance_of(model, [a, b], factor * cov_g, gain_scores=scores)
        scale = np.sqrt(np.diag(cov))
        eig = np.linalg.eigvalsh(cov / np.outer(scale, scale))
        assert eig.min() > -1e-9, (factor, eig.min())


def test_matched_root_maps_one_covariance_onto_the_other() -> None:
    rng = np.random.default_rng(3)
    x, y = rng.standard_normal((2, 5, 5))
    target, source = x @ x.T, y @ y.T
    t = matched_root(target, source)
    np.testing.assert_allclose(t @ source @ t.T, target, rtol=1e-9, atol=1e-9)
    # a source with a null direction: that direction maps to nothing
    v = np.linalg.qr(rng.standard_normal((5, 5)))[0]
    singular = (v[:, :4] * np.arange(1.0, 5.0)) @ v[:, :4].T
    t = matched_root(target, singular)
    np.testing.assert_allclose(t @ v[:, 4], 0.0, atol=1e-9)
    np.testing.assert_allclose(matched_root(target, np.zeros((5, 5))), 0.0)
