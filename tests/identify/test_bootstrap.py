"""The residual block bootstrap of the ML fit (``identify --bootstrap``).

Checked against what it does not share: the spread of the estimates over independent noise
seeds of a simulation (a small Monte Carlo), and the resampling against its definition.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.errors import InputError
from drivegain.identify import bootstrap as bs
from drivegain.identify import forked
from drivegain.identify.design import make_design
from drivegain.identify.gains import Estimator, estimate_gains
from drivegain.identify.ml import ml_fit
from drivegain.identify.mlmodel import run_pair

DURATION = 24.0
SEEDS = 12
REPLICATES = 30


def _design(world, run):
    bp = world.bases[world.robot.wrist_friction]
    return make_design(run, bp, world.robot.wrist_friction, world.robot)


def _pair(world, noisy_run, seed: int, **noise):
    rng = np.random.default_rng((23, seed))
    return (
        _design(world, noisy_run(0, None, rng, duration=DURATION, label="unloaded", **noise)),
        _design(
            world, noisy_run(1, world.payload, rng, duration=DURATION, label="loaded", **noise)
        ),
    )


def test_circular_blocks_are_stretches_of_consecutive_samples() -> None:
    rng = np.random.default_rng(5)
    idx = bs.circular_blocks(100, 13, rng)
    assert idx.shape == (100,) and idx.min() >= 0 and idx.max() < 100
    for start in range(0, 100, 13):
        block = idx[start : start + 13]
        assert np.all(np.diff(block) % 100 == 1)  # consecutive, wrapping past the end
    # Not the identity: the blocks start at random places.
    assert not np.array_equal(idx, np.arange(100))
    assert bs.block_length(231, 6) == 13 and bs.block_length(10**6, 6) == 100
    with pytest.raises(InputError, match="block of 0 samples"):
        bs.circular_blocks(100, 0, rng)


def test_bootstrap_sigma_matches_the_spread_over_noise_seeds(world, noisy_run) -> None:
    """Current noise of 1 % of rated current: the bootstrap σ of one seed against the standard
    deviation of the gains over independent seeds (which it never sees)."""
    rated = np.array([j.rated_current for j in world.robot.joints])
    noise = {"torque_noise": 0.0, "current_noise": 0.01 * rated}
    gains, boot = [], []
    for seed in range(SEEDS):
        a, b = _pair(world, noisy_run, seed, **noise)
        fit = ml_fit(a, b, world.payload)
        gains.append(fit.gains)
        if seed < 2:
            runs = run_pair(a, b, world.payload)
            spread = bs.bootstrap_fit(a, b, world.payload, fit, REPLICATES, runs=runs)
            assert spread.failed == 0 and spread.estimates.shape == (REPLICATES, 6 + 9)
            boot.append(spread.gain_std)
    monte_carlo = np.std(gains, axis=0, ddof=1)
    ratio = np.mean(boot, axis=0) / monte_carlo
    print(f"\nbootstrap σ / Monte Carlo spread per joint: {np.round(ratio, 2)}")
    # 12 seeds and 2 × 30 replicates: each ratio is uncertain by about ±40 %, their mean by ±20 %.
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio
    assert 0.75 < float(np.mean(ratio)) < 1.35, ratio


def test_replicates_split_between_processes_give_the_same_result(
    world, noisy_run, monkeypatch
) -> None:
    a, b = _pair(world, noisy_run, 0, torque_noise=0.1)
    fit = ml_fit(a, b, world.payload)
    runs = run_pair(a, b, world.payload)
    here = bs.bootstrap_fit(a, b, world.payload, fit, 10, runs=runs, parallel=False)
    monkeypatch.setattr(forked, "fork_is_safe", lambda: True)  # the suite's threads aside
    split = bs.bootstrap_fit(a, b, world.payload, fit, 10, runs=runs, parallel=True)
    np.testing.assert_array_equal(here.estimates, split.estimates)
    other_seed = bs.bootstrap_fit(a, b, world.payload, fit, 10, runs=runs, seed=1)
    assert not np.array_equal(here.estimates, other_seed.estimates)


def test_bootstrap_is_refused_where_it_does_not_apply(world, noisy_run) -> None:
    a, b = _pair(world, noisy_run, 0, torque_noise=0.1)
    apriori = world.robot.apriori_gains
    with pytest.raises(InputError, match="at least 10 replicates, got 3"):
        estimate_gains(a, b, world.payload, apriori, bootstrap=3)
    with pytest.raises(InputError, match="use it with --estimator ml"):
        estimate_gains(a, b, world.payload, apriori, estimator=Estimator.PAPER, bootstrap=10)
