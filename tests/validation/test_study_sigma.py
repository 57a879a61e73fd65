"""benchmarks/study_sigma.py at small size: its study seeds are the validation study's own draws,
its held-trajectory draws do not depend on the split between processes, and the interval of
its spreads has its coverage."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from drivegain.errors import IdentificationError
from drivegain.validation.estimators import METHODS, OURS, run_seed
from drivegain.validation.scenarios import SCENARIOS
from drivegain.validation.world import make_world

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from study_sigma import identify_draws, std_interval, study_seeds, study_trajectories

KEY = "random-current-1pct"


def test_study_seeds_are_the_validation_studys_draws(capsys: pytest.CaptureFixture[str]) -> None:
    d = study_seeds(KEY, 3, 5, workers=1)
    out = capsys.readouterr().out
    assert f"{KEY}, study seeds 3-4 (2)" in out and "pooled coverage of ±2σ" in out
    assert "| std of z |" in out and "| mean of z |" in out
    # the validation study's own seed 4 (its excitation, its noise), our estimator alone
    scenario = next(s for s in SCENARIOS if s.key == KEY)
    ours = tuple(m for m in METHODS if m.key == OURS)
    seed = run_seed(make_world(), 4, scenario, ours)
    np.testing.assert_allclose(d.gains[1], seed.gains[OURS], rtol=1e-12)
    np.testing.assert_allclose(d.sigma[1], seed.std[OURS], rtol=1e-12)


def test_held_trajectory_draws(capsys: pytest.CaptureFixture[str]) -> None:
    (d,) = study_trajectories(KEY, [5], draws=4, workers=2)
    out = capsys.readouterr().out
    assert f"{KEY}, trajectory 5: 4 draws" in out
    for row in ("scatter of the gains / mean σ", "std of z about its mean", "mean z against"):
        assert row in out
    assert d.gains.shape == d.sigma.shape == d.repeat.shape == (4, 6)
    assert np.all(d.repeat >= 1.0) and np.all(d.sigma > 0.0)
    assert np.all(np.ptp(d.gains, axis=0) > 0.0)  # each draw its own noise
    assert np.max(np.abs(d.z)) < 10.0  # near the truth at 1 % current noise
    # one process gives the same draws, in the same order, as two
    alone = identify_draws(KEY, d.seeds, 5, workers=1)
    np.testing.assert_array_equal(alone.gains, d.gains)
    np.testing.assert_array_equal(alone.sigma, d.sigma)


def test_a_failed_fit_is_counted_and_left_out(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from drivegain.identify import ml

    fit, calls = ml.ml_fit, []

    def second_fails(*args: object, **kwargs: object) -> ml.MLFit:
        calls.append(1)
        if len(calls) == 2:
            raise IdentificationError("the gains grow without bound (test)")
        return fit(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(ml, "ml_fit", second_fails)
    d = study_seeds(KEY, 3, 6, workers=1)
    assert d.seeds == [3, 5] and d.failed == [4] and d.gains.shape == (2, 6)
    assert np.all(np.isfinite(d.gains)) and np.all(np.isfinite(d.sigma))
    assert "1 fit(s) failed, left out (seeds 4)" in capsys.readouterr().out


def test_the_spread_interval_covers_the_true_spread() -> None:
    rng = np.random.default_rng(7)
    draws, trials = 30, 2000
    scale = np.array([0.5, 2.0])
    covered = np.zeros(2)
    for _ in range(trials):
        _, (lo, hi) = std_interval(rng.normal(size=(draws, 2)) * scale)
        covered += (lo <= scale) & (scale <= hi)
    assert np.all(np.abs(covered / trials - 0.95) < 0.015)


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(SystemExit, match="--scenario: expected one of"):
        study_seeds("torque-7", 0, 4)
    with pytest.raises(SystemExit, match="need 2 draws or more"):
        study_trajectories(KEY, [0], draws=1)
    with pytest.raises(ValueError, match="need 2 draws"):
        std_interval(np.zeros((1, 6)))
