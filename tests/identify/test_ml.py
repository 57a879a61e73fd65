"""The maximum-likelihood gain estimator, its HAC covariance and the errors-in-variables test.

Checked against independent facts: noise-free simulations (exact answers), the long-run
variance of an AR(1) process (closed form), and a small Monte Carlo with current noise on
non-optimised excitations, where plain least squares is visibly attenuated.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from drivegain.errors import IdentificationError, InputError
from drivegain.identify.compare import global_ls_gains
from drivegain.identify.design import make_design
from drivegain.identify.eiv import eiv_test
from drivegain.identify.gains import Estimator, estimate_gains, identify_gains
from drivegain.identify.hac import bartlett_lag, long_run_covariance, sandwich
from drivegain.identify.ml import ml_fit

RATE = 250.0
DURATION = 24.0
SEEDS = 6


def _base(world):
    return world.bases[world.robot.wrist_friction]


def _rel(a, b) -> np.ndarray:
    return np.abs(np.asarray(a, float) / np.asarray(b, float) - 1.0)


def _design(world, run):
    return make_design(run, _base(world), world.robot.wrist_friction, world.robot)


def _exact_pair(world, exact_run):
    return (
        _design(world, exact_run(0, None, label="unloaded")),
        _design(world, exact_run(1, world.payload, label="loaded")),
    )


def test_exact_data_give_the_true_gains_and_payload(world, exact_run) -> None:
    a, b = _exact_pair(world, exact_run)
    fit = ml_fit(a, b, world.payload)
    assert fit.converged
    assert np.max(_rel(fit.gains, world.truth.gains)) < 1e-7
    unknown = [i for i, k in enumerate(world.payload.known_mask()) if not k]
    np.testing.assert_allclose(
        fit.payload_unknown, world.payload.values[unknown], rtol=1e-6, atol=1e-9
    )
    # The paper's estimator agrees on exact data: two different solvers, one answer.
    paper = identify_gains(a, b, world.payload, world.robot.apriori_gains)
    assert np.max(_rel(fit.gains, paper.gains)) < 1e-6


def test_estimator_choice_and_alpha(world, exact_run) -> None:
    a, b = _exact_pair(world, exact_run)
    res = estimate_gains(a, b, world.payload, world.robot.apriori_gains)
    assert res.estimator is Estimator.ML and res.ml is not None and res.eiv is not None
    assert res.fit is None and res.alpha_curve == []
    paper = estimate_gains(
        a, b, world.payload, world.robot.apriori_gains, estimator=Estimator.PAPER, alpha=1.0
    )
    assert paper.fit is not None and paper.fit.alpha == 1.0
    with pytest.raises(InputError, match="paper"):
        estimate_gains(a, b, world.payload, world.robot.apriori_gains, alpha=1.0)


def test_identical_runs_are_refused(world, exact_run) -> None:
    """Run b carrying no payload information cannot set the scale."""
    a = _design(world, exact_run(0, None, label="unloaded"))
    with pytest.raises(IdentificationError, match="loaded run"):
        ml_fit(a, a, world.payload)


# --------------------------------------------------------------------------------------------
# HAC


def _ar1(rng: np.random.Generator, rho: float, n: int) -> np.ndarray:
    e = rng.normal(size=n)
    x = np.empty(n)
    x[0] = e[0] / np.sqrt(1 - rho**2)
    for k in range(1, n):
        x[k] = rho * x[k - 1] + e[k]
    return x


def test_long_run_variance_of_ar1_matches_the_closed_form() -> None:
    """Var(mean) of AR(1): σ_e²/(1 − ρ)² / N; the naive estimate misses it by (1+ρ)/(1−ρ)."""
    rng = np.random.default_rng(4)
    rho, n, reps = 0.6, 4000, 200
    ratios = []
    for _ in range(reps):
        x = _ar1(rng, rho, n)[:, None]
        x = x - x.mean()
        lag = bartlett_lag([x])
        ratios.append(long_run_covariance([x], lag)[0, 0] / n)
    truth = 1.0 / (1.0 - rho) ** 2
    assert abs(np.mean(ratios) / truth - 1.0) < 0.1
    naive = 1.0 / (1.0 - rho**2)
    assert abs(naive / truth - 1.0) > 0.5  # the correction matters here


def test_lag_follows_the_correlation() -> None:
    rng = np.random.default_rng(5)
    white = rng.normal(size=(5000, 3))
    assert bartlett_lag([white]) <= 2
    assert bartlett_lag([_ar1(rng, 0.9, 5000)[:, None]]) > 10


def test_sandwich_is_ols_covariance_for_white_noise() -> None:
    """Lag 0, homoscedastic errors: H⁻¹SH⁻¹ → σ²(XᵀX)⁻¹, the textbook OLS covariance."""
    rng = np.random.default_rng(6)
    x = rng.normal(size=(20000, 3))
    e = 0.5 * rng.normal(size=20000)
    scores = x * e[:, None]
    cov = sandwich(x.T @ x, long_run_covariance([scores], 0), 20000, 3)
    expected = 0.25 * np.linalg.inv(x.T @ x)
    np.testing.assert_allclose(cov, expected, atol=0.05 * float(np.max(np.diag(expected))))


# --------------------------------------------------------------------------------------------
# Current noise on ordinary (non-optimised) excitations: a small Monte Carlo


@pytest.fixture(scope="module")
def current_noise_seeds(world, noisy_run) -> Iterator[list[tuple[object, object]]]:
    """Designs (a, b) of SEEDS seeds, white noise of 1 % rated current on every drive."""
    rated = np.array([j.rated_current for j in world.robot.joints])
    out = []
    for seed in range(SEEDS):
        rng = np.random.default_rng((17, seed))
        runs = [
            noisy_run(
                which,
                payload,
                rng,
                duration=DURATION,
                torque_noise=0.0,
                current_noise=0.01 * rated,
                label=label,
            )
            for which, payload, label in ((0, None, "unloaded"), (1, world.payload, "loaded"))
        ]
        out.append(tuple(_design(world, r) for r in runs))
    yield out


def test_ml_is_unbiased_and_honest_under_current_noise(world, current_noise_seeds) -> None:
    """ML: |mean z| small and pooled ±2σ coverage near 95 %; plain LS: attenuated, |z| large."""
    truth = world.truth.gains
    z_ml, z_ls, p_values = [], [], []
    for a, b in current_noise_seeds:
        fit = ml_fit(a, b, world.payload)
        z_ml.append((fit.gains - truth) / fit.gain_std)
        ls = global_ls_gains(a, b, world.payload)
        assert ls.std is not None
        z_ls.append((ls.gains - truth) / ls.std)
        p_values.append(eiv_test(fit, a, b, world.payload).p_value)
    z_ml_a, z_ls_a = np.array(z_ml), np.array(z_ls)
    print(f"\nML mean z {np.round(z_ml_a.mean(0), 2)}, sd {np.round(z_ml_a.std(0), 2)}")
    print(f"LS mean z {np.round(z_ls_a.mean(0), 2)}; DWH p {np.round(p_values, 4)}")
    coverage = float(np.mean(np.abs(z_ml_a) < 2.0))
    assert coverage >= 0.85, coverage
    # With 6 seeds the mean of an honest z has a standard error of 0.41.
    assert np.all(np.abs(z_ml_a.mean(0)) < 1.3)
    assert np.sqrt(np.mean(z_ml_a**2)) < 1.5
    # The same check fails plain LS: its gains are attenuated by the noisy currents.
    assert np.max(np.abs(z_ls_a.mean(0))) > 3.0
    # And the errors-in-variables test says so on every seed.
    assert max(p_values) < 0.01


def test_eiv_test_is_quiet_when_the_currents_are_nearly_exact(world, noisy_run) -> None:
    """Tiny torque noise: LS's attenuation is far below its σ, the test rejects rarely."""
    rejections = 0
    for seed in range(4):
        rng = np.random.default_rng((23, seed))
        a = noisy_run(0, None, rng, torque_noise=0.002, duration=DURATION, label="unloaded")
        b = noisy_run(1, world.payload, rng, torque_noise=0.002, duration=DURATION, label="loaded")
        da, db = _design(world, a), _design(world, b)
        fit = ml_fit(da, db, world.payload)
        test = eiv_test(fit, da, db, world.payload)
        print(f"seed {seed}: statistic {test.statistic:.3g} ({test.dof} dof), p {test.p_value:.3g}")
        rejections += test.biased
    assert rejections <= 1
