"""The time base of a run: irregular stamps detected, resampled, or refused (issue 16, item 1)."""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.errors import DataError
from drivegain.identify.timebase import analyse_time_base, uniform_samples


def _irregular(n: int, seed: int = 0) -> np.ndarray:
    """Stamps whose steps are 10 or 12 ms at random (a controller logging at 'about 91 Hz')."""
    steps = np.random.default_rng(seed).choice([0.010, 0.012], n - 1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def test_uniform_stamps_pass_unchanged() -> None:
    t = np.arange(500) * 0.004
    cycle = np.arange(500)
    tb = analyse_time_base(t, cycle, 0.004)
    assert tb.uniform and tb.spread < 1e-9 and tb.period_s == pytest.approx(0.004)
    q = np.random.default_rng(1).standard_normal((500, 2))
    qu, _, tb2, notes = uniform_samples(t, cycle, q, 2 * q, 0.004)
    assert qu is q and notes == [] and tb2.uniform


def test_irregular_stamps_are_detected_with_their_spread() -> None:
    t = _irregular(2000)
    steps = np.diff(t)
    tb = analyse_time_base(t, np.arange(t.size), float(steps.mean()))
    assert not tb.uniform
    # Independent: the RMS spread of the steps about their mean, relative to the mean.
    assert tb.spread == pytest.approx(np.std(steps) / steps.mean(), rel=1e-9)
    assert tb.spread == pytest.approx(1.0 / 11.0, rel=0.05)  # steps 11 ± 1 ms
    assert tb.min_step_s == pytest.approx(0.010) and tb.max_step_s == pytest.approx(0.012)
    assert "irregular time stamps" in tb.note() and "10–12 ms" in tb.note()


def test_declared_period_disagreeing_with_the_stamps_is_refused() -> None:
    t = _irregular(2000)  # mean step 11 ms
    with pytest.raises(DataError) as err:
        analyse_time_base(t, np.arange(t.size), 0.010, path="run.mcap")
    msg = str(err.value)
    assert msg.startswith("run.mcap: ") and "\n" not in msg
    assert "sync_period_s declares 10 ms" in msg and "11" in msg


def test_resampling_reproduces_the_signal_on_a_uniform_grid() -> None:
    t = _irregular(3000, seed=3)
    f = 0.7  # Hz
    q = np.column_stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * 2 * f * t)])
    cur = np.column_stack([np.cos(2 * np.pi * f * t), t])
    qu, vu, tb, notes = uniform_samples(t, np.arange(t.size), q, cur, float(np.diff(t).mean()))
    grid = np.arange(qu.shape[0]) * tb.period_s
    # Independent: the functions evaluated at the uniform grid times.
    assert np.max(np.abs(qu[:, 0] - np.sin(2 * np.pi * f * grid))) < 1e-6
    assert np.max(np.abs(qu[:, 1] - np.cos(2 * np.pi * 2 * f * grid))) < 1e-5
    assert np.max(np.abs(vu[:, 1] - grid)) < 1e-9  # a straight line stays exact
    assert np.max(np.abs(vu[:, 0] - np.cos(2 * np.pi * f * grid))) < 1e-6
    assert grid[-1] <= t[-1] + 1e-12 and notes and "resampled" in notes[0]


def test_missing_cycles_on_a_uniform_base_are_still_filled() -> None:
    cycle = np.delete(np.arange(1000), [100, 500])
    t = cycle * 0.004
    q = np.sin(0.01 * cycle)[:, None]
    qu, _, tb, notes = uniform_samples(t, cycle, q, q, 0.004)
    assert tb.uniform and qu.shape == (1000, 1)
    assert notes == ["2 missing SYNC cycles filled by linear interpolation"]


def test_long_gaps_in_an_irregular_base_are_refused() -> None:
    t = _irregular(2000)
    t[1000:] += 0.5  # a 0.5 s hole: ~45 periods
    with pytest.raises(DataError, match="too many to interpolate"):
        uniform_samples(
            t,
            np.arange(t.size),
            np.zeros((t.size, 1)),
            np.zeros((t.size, 1)),
            (t[-1] - t[0]) / (t.size - 1),
        )
