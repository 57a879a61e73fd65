"""The currents' age (``--current-delay``): period-mean currents re-aligned onto the positions."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from drivegain.errors import InputError
from drivegain.identify.prepare import aligned_current
from drivegain.identify.signal import FilterSettings, default_filter

RATE_HZ = 250.0
T = 1.0 / RATE_HZ


def _period_means(freq_hz: float, t: np.ndarray) -> np.ndarray:
    """What a drive reports at t_k: sin(ωt) averaged over [t_k − T, t_k] (exact integral)."""
    w = 2 * np.pi * freq_hz
    return (np.cos(w * (t - T)) - np.cos(w * t)) / (w * T)


@pytest.mark.parametrize("freq_hz", [0.5, 2.0, 5.0])
def test_half_a_sample_realigns_period_means_with_the_positions(freq_hz: float) -> None:
    t = np.arange(2000) * T
    truth = np.sin(2 * np.pi * freq_hz * t)[:-1]
    reported = _period_means(freq_hz, t)[:, None]
    raw_error = np.abs(reported[:-1, 0] - truth).max()
    aligned_error = np.abs(aligned_current(reported, 0.5)[:-1, 0] - truth).max()
    # The raw mean lags by T/2 (error ≈ ω·T/2); aligned, what is left is second order in ω·T.
    assert raw_error == pytest.approx(np.pi * freq_hz * T, rel=0.05)
    assert aligned_error < 0.2 * (2 * np.pi * freq_hz * T) ** 2


def test_zero_delay_leaves_the_currents_untouched_and_the_last_sample_is_kept() -> None:
    c = np.arange(12.0).reshape(6, 2)
    assert aligned_current(c, 0.0) is c
    out = aligned_current(c, 0.25)
    assert np.array_equal(out[-1], c[-1])
    assert np.allclose(out[:-1], 0.75 * c[:-1] + 0.25 * c[1:])


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan")])
def test_a_delay_outside_one_sample_is_refused(bad: float) -> None:
    with pytest.raises(InputError, match="current_delay"):
        FilterSettings(cutoff_hz=5.0, decimate=2, trim=1, current_delay=bad)


def test_default_filter_carries_the_delay() -> None:
    assert default_filter(RATE_HZ, 0.5, current_delay=0.5).current_delay == 0.5
    assert default_filter(RATE_HZ, 0.5).current_delay == 0.0


def test_the_command_line_refuses_more_than_one_sample(tmp_path) -> None:
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "drivegain",
            "identify",
            "--robot",
            "tx40",
            "--unloaded",
            str(tmp_path / "a.mcap"),
            "--out",
            str(tmp_path / "out"),
            "--current-delay",
            "2",
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert "--current-delay" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists()
