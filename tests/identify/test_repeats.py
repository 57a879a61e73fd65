"""Errors that repeat with a periodic excitation: phase bins and the σ that counts them.

Checked against a Monte Carlo of a linear regression whose error is a pattern drawn afresh
each time and repeated every period (the spread of the estimate over draws is the truth), and
against white errors, where nothing repeats and σ must stay as it was. The ML's σ on the
closed-loop drives, whose sticking at reversals repeats every period, is checked in the
validation study (docs/validation.md).
"""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.errors import UsageError
from drivegain.identify.estimate import cluster_sums
from drivegain.identify.hac import MIN_PERIODS, gathered, phase_bins, with_repeats
from drivegain.identify.ml import MIN_LAG

PHASES = 80  # samples per period
PERIODS = 6
LAG = MIN_LAG  # the ML's shortest lag


def test_phase_bins_give_each_sample_its_phase() -> None:
    rate, period = 12.5, 8.0
    t = 3.0 + np.arange(400) / rate
    keep = np.ones(t.size, dtype=bool)
    keep[50:70] = False  # samples at rest taken out: gaps do not shift the phase
    labels, bins = phase_bins(t[keep], period, rate)
    assert bins == 100
    expected = (np.arange(400) % 100)[keep]
    np.testing.assert_array_equal(labels, expected)


def test_phase_bins_need_a_period_and_enough_of_it() -> None:
    t = np.arange(200) / 10.0  # 19.9 s
    assert phase_bins(t, None, 10.0) is None
    assert phase_bins(t, 19.9 / MIN_PERIODS * 1.01, 10.0) is None
    assert phase_bins(t, 19.9 / MIN_PERIODS * 0.99, 10.0) is not None
    with pytest.raises(UsageError, match="rate_hz"):
        phase_bins(t, 5.0, 0.0)


def _regression(rng: np.random.Generator, repeat: bool) -> tuple[np.ndarray, ...]:
    """Periodic regressors; errors: white, or a smooth pattern repeated every period."""
    phase = np.arange(PHASES * PERIODS) % PHASES
    x = np.column_stack(
        [
            np.sin(2 * np.pi * phase / PHASES),
            np.cos(2 * np.pi * 3 * phase / PHASES),
            1.0 + 0.3 * np.sin(2 * np.pi * 2 * phase / PHASES),
        ]
    )
    e = 0.3 * rng.normal(size=phase.size)
    if repeat:
        # correlated over 2 samples, well inside the lag (a Bartlett window shrinks longer ones)
        pattern = np.convolve(rng.normal(size=PHASES + 2), np.ones(3) / 3, mode="valid")
        e = e + pattern[phase]
    return x, e, phase


def _sigmas(
    x: np.ndarray, e: np.ndarray, phase: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The estimate's error, its σ from with_repeats, and the white-noise σ it raised."""
    h = x.T @ x
    err = np.linalg.solve(h, x.T @ e)
    r = e - x @ err
    rows, p = x.shape
    cov = np.linalg.inv(h) * (r @ r) / (rows - p)  # what a short-range estimate says
    folded = cluster_sums(x * r[:, None], phase, PHASES)
    raised, scale = with_repeats(cov, h, [folded], LAG, rows)
    assert np.all(scale >= 1.0)
    np.testing.assert_allclose(raised, cov * np.outer(scale, scale))
    return err, np.sqrt(np.diag(raised)), np.sqrt(np.diag(cov))


def test_sigma_of_repeated_errors_matches_their_spread() -> None:
    rng = np.random.default_rng(11)
    draws = [_sigmas(*_regression(rng, repeat=True)) for _ in range(400)]
    spread = np.std([d[0] for d in draws], axis=0)
    sigma = np.sqrt(np.mean([d[1] ** 2 for d in draws], axis=0))
    white = np.sqrt(np.mean([d[2] ** 2 for d in draws], axis=0))
    print(f"\nspread {spread}, σ raised {sigma}, white σ {white}")
    # The white-noise σ misses the repeats by about √PERIODS. Counted by phase, σ comes within
    # a quarter of the spread. It stays below it: the residuals lack what the fit took into
    # the estimate, the slow content the repeats carry (0.93 of the spread from the true
    # errors, 0.76 from the residuals, in this set-up), so the correction is a lower bound.
    assert np.all(white < 0.6 * spread)
    assert np.all(sigma > 0.7 * spread)
    assert np.all(sigma < 1.05 * spread)


def test_white_errors_keep_their_sigma() -> None:
    rng = np.random.default_rng(12)
    ratios = []
    for _ in range(200):
        x, e, phase = _regression(rng, repeat=False)
        h = x.T @ x
        r = e - x @ np.linalg.solve(h, x.T @ e)
        cov = np.linalg.inv(h) * (r @ r) / (x.shape[0] - 3)
        folded = cluster_sums(x * r[:, None], phase, PHASES)
        ratios.append(with_repeats(cov, h, [folded], LAG, x.shape[0])[1])
    # Raised only where the noisier phase-summed estimate happens to come out larger: a few
    # per cent on average, never a factor.
    assert float(np.mean(ratios)) < 1.1
    assert float(np.median(ratios)) < 1.05


def test_phase_bins_from_the_excitation_start_line_runs_up() -> None:
    """Two runs of one excitation started at different times of their logs: measured from each
    run's excitation start, the same pose has the same bin in both."""
    rate, period = 10.0, 5.0
    a = phase_bins(1.0 + np.arange(200) / rate, period, rate, origin_s=3.0)
    b = phase_bins(7.3 + np.arange(200) / rate, period, rate, origin_s=9.3)
    assert a is not None and b is not None
    np.testing.assert_array_equal(a[0], b[0])
    assert a[0][20] == 0  # t = 3.0 s: the excitation's phase 0
    # from their first samples instead, the two runs' bins would not line up
    first = phase_bins(7.3 + np.arange(200) / rate, period, rate)
    assert first is not None and not np.array_equal(first[0], a[0])


def test_phase_sums_are_gathered_per_run_or_together() -> None:
    a, b = np.ones((4, 2)), 2.0 * np.ones((4, 2))
    assert gathered([a, None], together=True) is None  # a run without phases: none at all
    assert gathered([], together=False) is None
    each = gathered([a, b], together=False)
    assert each is not None and len(each) == 2
    (both,) = gathered([a, b], together=True) or []
    np.testing.assert_array_equal(both, 3.0 * np.ones((4, 2)))
    # different bins (another rate or period) cannot be added
    apart = gathered([a, np.ones((5, 2))], together=True)
    assert apart is not None and len(apart) == 2
