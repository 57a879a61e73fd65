"""Filtering, differentiation and parallel decimation against analytic signals."""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.errors import DataError, InputError, UsageError
from drivegain.identify import decimate as dec
from drivegain.identify.decimate import (
    decimate_columns,
    decimated_length,
    decimation_stages,
    first_equal,
    parallel_decimate,
)
from drivegain.identify.signal import FilterSettings, default_filter, derivatives


def fourier(t: np.ndarray, base_hz: float, harmonics: int, n: int, seed: int):
    """Sum of sinusoids per joint (the excitation's form) with exact derivatives."""
    rng = np.random.default_rng(seed)
    q = np.zeros((t.size, n))
    qd = np.zeros_like(q)
    qdd = np.zeros_like(q)
    for j in range(n):
        for h in range(1, harmonics + 1):
            w = 2 * np.pi * base_hz * h
            a, phi = rng.normal() / h, rng.uniform(0, 2 * np.pi)
            q[:, j] += a * np.sin(w * t + phi)
            qd[:, j] += a * w * np.cos(w * t + phi)
            qdd[:, j] -= a * w * w * np.sin(w * t + phi)
    return q, qd, qdd


def rel_err(x: np.ndarray, ref: np.ndarray) -> float:
    return float(np.abs(x - ref).max() / np.abs(ref).max())


@pytest.mark.parametrize(("rate", "base", "harmonics"), [(250.0, 0.1, 5), (1000.0, 0.2, 6)])
def test_derivatives_match_analytic_inside_trimmed_interior(rate, base, harmonics) -> None:
    t = np.arange(int(60 * rate)) / rate
    q, qd, qdd = fourier(t, base, harmonics, 6, seed=1)
    fs = default_filter(rate, base * harmonics)
    qf, qd_e, qdd_e = derivatives(q, rate, fs)
    border = fs.trim * fs.decimate
    inner = slice(border, t.size - border)
    assert rel_err(qf[inner], q[inner]) < 1e-6
    assert rel_err(qd_e[inner], qd[inner]) < 1e-4
    assert rel_err(qdd_e[inner], qdd[inner]) < 1e-3


def test_derivatives_with_encoder_quantisation() -> None:
    rate = 250.0
    t = np.arange(int(60 * rate)) / rate
    q, qd, qdd = fourier(t, 0.1, 5, 6, seed=2)
    quantum = np.deg2rad(1e-3)  # model.md: 1e-3 degree at the joint
    q_meas = np.round(q / quantum) * quantum
    fs = default_filter(rate, 0.5)
    _, qd_e, qdd_e = derivatives(q_meas, rate, fs)
    inner = slice(fs.trim * fs.decimate, t.size - fs.trim * fs.decimate)
    assert rel_err(qd_e[inner], qd[inner]) < 1e-3
    assert rel_err(qdd_e[inner], qdd[inner]) < 1e-2
    # without the low-pass, differences of quantised positions are far noisier
    raw_qdd = np.gradient(np.gradient(q_meas, 1 / rate, axis=0), 1 / rate, axis=0)
    assert rel_err(raw_qdd[inner], qdd[inner]) > 10 * rel_err(qdd_e[inner], qdd[inner])


def test_one_dimensional_input() -> None:
    rate = 500.0
    t = np.arange(5000) / rate
    q = np.sin(2 * np.pi * 0.7 * t)
    fs = default_filter(rate, 0.7)
    qf, qd, qdd = derivatives(q, rate, fs)
    assert qf.shape == qd.shape == qdd.shape == (5000,)
    inner = slice(fs.trim * fs.decimate, 5000 - fs.trim * fs.decimate)
    assert rel_err(qd[inner], 2 * np.pi * 0.7 * np.cos(2 * np.pi * 0.7 * t[inner])) < 1e-4


def test_parallel_decimation_keeps_the_linear_model() -> None:
    """Y = W χ before decimation => Y_d = W_d χ after: the same filter acts on every column."""
    rng = np.random.default_rng(4)
    rate, n_samples, n, p = 250.0, 6000, 6, 12
    t = np.arange(n_samples) / rate
    # Columns with slow content plus broadband noise (which the decimation must remove alike).
    w = np.sin(2 * np.pi * rng.uniform(0.05, 2, size=(1, n, p)) * t[:, None, None])
    w += 0.3 * rng.normal(size=(n_samples, n, p))
    chi = rng.normal(size=p) * np.logspace(-2, 2, p)
    y = w @ chi
    fs = default_filter(rate)
    w_d, y_d = parallel_decimate([w, y], fs.decimate, fs.trim)
    assert w_d.shape == (decimated_length(n_samples, fs.decimate) - 2 * fs.trim, n, p)
    assert y_d.shape == w_d.shape[:2]
    assert rel_err(w_d @ chi, y_d) < 1e-12
    # and something was filtered: plain subsampling would keep the noise
    assert np.std(w_d - w[:: fs.decimate][fs.trim : -fs.trim]) > 0.1


@pytest.mark.parametrize("factor", [8, 40, 17])
def test_decimation_removes_what_would_alias_and_keeps_the_band(factor: int) -> None:
    rate = 2000.0
    n_samples = 200 * factor
    t = np.arange(n_samples) / rate
    f_new = rate / factor
    low = np.sin(2 * np.pi * 0.05 * f_new * t + 0.3)
    high = np.sin(2 * np.pi * 0.77 * rate / 2 * t + 0.7)  # far above the new Nyquist frequency
    trim = 30
    (x_d,) = parallel_decimate([low + high], factor, trim)
    expected = low[::factor][trim:-trim]  # output k is input (trim + k)·factor
    assert x_d.shape == expected.shape
    # Pass-band ripple: 0.05 dB per Chebyshev stage, twice (forward and backward).
    ripple = 1 - 10 ** (-0.05 * 2 * len(decimation_stages(factor)) / 20)
    assert rel_err(x_d, expected) < ripple + 2e-3  # and the high part gone
    naive = (low + high)[::factor][trim:-trim]
    assert rel_err(naive, expected) > 0.1  # plain subsampling would alias it


def test_trim_covers_the_border_transients() -> None:
    """Processing a record gives the same interior as processing a much longer one."""
    for rate, bandwidth in [(250.0, None), (250.0, 0.5), (5000.0, None)]:
        fs = default_filter(rate, bandwidth)
        f = fs.decimate
        n_samples = int(30 * rate) // f * f
        pad = (n_samples // 2) // f * f
        t = np.arange(-pad, n_samples + pad) / rate
        q, _, _ = fourier(t, (bandwidth or 2.0) / 5, 5, 3, seed=5)
        _, _, a_long = derivatives(q, rate, fs)
        _, _, a_short = derivatives(q[pad : pad + n_samples], rate, fs)
        (d_long,) = parallel_decimate([a_long], f, 0)
        (d_short,) = parallel_decimate([a_short], f, fs.trim)
        ref = d_long[pad // f + fs.trim : pad // f + fs.trim + d_short.shape[0]]
        assert rel_err(d_short, ref) < 2e-4, (rate, bandwidth)


def test_default_filter_rules() -> None:
    for rate in (100.0, 250.0, 1000.0, 5000.0):
        for bw in (None, 0.3, 1.0):
            fs = default_filter(rate, bw)
            assert 0 < fs.cutoff_hz <= min(rate / 20, 50.0)
            if bw is not None:
                assert fs.cutoff_hz >= 2 * bw
            assert 0.4 * rate / fs.decimate >= fs.cutoff_hz * 0.999  # band kept
            assert fs.trim >= 1
    assert default_filter(5000.0).cutoff_hz == 50.0
    assert default_filter(250.0).cutoff_hz == 12.5
    assert default_filter(250.0, 0.5).cutoff_hz == 5.0
    fs = default_filter(1000.0, cutoff_hz=20.0, decimate=5)
    assert (fs.cutoff_hz, fs.decimate) == (20.0, 5)
    # a lower cut-off rings longer: more seconds trimmed
    seconds = [(f.trim * f.decimate / 1000.0) for f in (fs, default_filter(1000.0, cutoff_hz=5.0))]
    assert seconds[0] < seconds[1]


def test_decimation_stages() -> None:
    assert decimation_stages(1) == []
    assert decimation_stages(8) == [8]
    assert np.prod(decimation_stages(400)) == 400 and max(decimation_stages(400)) <= 10
    assert decimation_stages(34) == [17, 2]


@pytest.mark.parametrize(
    ("call", "error", "fragment"),
    [
        (lambda: default_filter(250.0, cutoff_hz=125.0), InputError, "Nyquist frequency 125"),
        (lambda: default_filter(250.0, cutoff_hz=-1.0), InputError, "cut-off -1.0 Hz"),
        (lambda: default_filter(0.0), InputError, "positive number of Hz"),
        (lambda: default_filter(float("nan")), InputError, "positive number of Hz"),
        (lambda: default_filter(250.0, 20.0), InputError, "too low for a trajectory"),
        (lambda: default_filter(250.0, 0.5, cutoff_hz=0.4), InputError, "would remove"),
        (lambda: default_filter(250.0, 0.5, decimate=300), InputError, "keeps only up to"),
        (lambda: default_filter(250.0, decimate=0), InputError, "integer >= 1"),
        (lambda: FilterSettings(cutoff_hz=5.0, decimate=2, trim=-1), InputError, "trim"),
        (lambda: FilterSettings(cutoff_hz=0.0, decimate=2, trim=1), InputError, "cutoff"),
    ],
)
def test_bad_settings(call, error, fragment) -> None:
    with pytest.raises(error) as exc:
        call()
    assert fragment in str(exc.value) and "\n" not in str(exc.value)


def test_bad_data() -> None:
    fs = FilterSettings(cutoff_hz=10.0, decimate=4, trim=5)
    with pytest.raises(DataError, match=r"run\.mcap: too few samples for the position filter: 10"):
        derivatives(np.zeros((10, 6)), 250.0, fs, source="run.mcap")
    with pytest.raises(InputError, match="Nyquist"):
        derivatives(np.zeros((100, 6)), 15.0, fs)
    q = np.zeros((100, 2))
    q[42, 1] = np.nan
    with pytest.raises(DataError, match=r"not finite .* at sample 42"):
        derivatives(q, 250.0, fs)
    with pytest.raises(DataError, match="too few samples to decimate by 4"):
        parallel_decimate([np.zeros((20, 3))], 4, 0)
    with pytest.raises(DataError, match="leave 25, not more than the 30 border samples"):
        parallel_decimate([np.zeros((100, 3))], 4, 15)
    with pytest.raises(InputError, match="integer >= 1"):
        parallel_decimate([np.zeros((100, 3))], 0, 1)
    with pytest.raises(UsageError, match="expected 100 samples"):
        parallel_decimate([np.zeros((100, 3)), np.zeros((99, 3))], 2, 1)


def test_factor_one_only_trims() -> None:
    x = np.arange(50.0).reshape(25, 2)
    (y,) = parallel_decimate([x], 1, 3)
    np.testing.assert_array_equal(y, x[3:-3])


@pytest.mark.parametrize("factor", [4, 17], ids=["iir", "fir"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_sample_is_named_by_its_index(factor: int, bad: float) -> None:
    x = np.random.default_rng(1).normal(size=(2000, 3))
    x[1234, 2] = bad
    with pytest.raises(DataError, match=r"array 1 is not finite \(NaN or inf\) at sample 1234"):
        parallel_decimate([np.ones((2000, 2)), x], factor, 2, source="run.mcap")


def test_first_equal_names_the_first_of_each_group() -> None:
    a = np.arange(6.0)
    v = np.column_stack([a, a + 1, a, -a, a + 1, a])
    np.testing.assert_array_equal(first_equal(v), [0, 1, 0, 3, 1, 0])


def test_equal_columns_are_filtered_once_with_the_same_numbers(monkeypatch) -> None:
    rng = np.random.default_rng(2)
    base = rng.normal(size=(3000, 4))
    x = np.column_stack([base, base[:, 1], base[:, 3], base[:, 1], rng.normal(size=3000)])
    x[:, -1] = base[:, 0]
    x[1500, -1] += 1.0  # said to equal column 0, but not here: filtered on its own
    same_as = np.array([0, 1, 2, 3, 1, 3, 1, 0])
    widths: list[int] = []
    decimate = dec.parallel_decimate

    def counting(arrays, *a, **k):
        widths.append(arrays[0].shape[1])
        return decimate(arrays, *a, **k)

    monkeypatch.setattr(dec, "parallel_decimate", counting)
    monkeypatch.setattr(dec, "SERIES_BLOCK", 3)
    for factor in (1, 6):
        widths.clear()
        got = decimate_columns(x, factor, same_as)
        (alone,) = decimate([x], factor, 0)
        np.testing.assert_array_equal(got, alone)  # bit for bit
        assert sum(widths) == 5 and max(widths) == 3
    np.testing.assert_array_equal(decimate_columns(x, 6), alone)
    # the columns to filter side by side (repeats last): taken as slices, the same numbers
    y = x[:, :7]
    widths.clear()
    np.testing.assert_array_equal(decimate_columns(y, 6, same_as[:7]), decimate([y], 6, 0)[0])
    assert widths == [3, 1]


@pytest.mark.parametrize("factor", [6, 17, 60])  # one IIR stage, decimate's FIR, two stages
def test_decimation_is_the_same_for_any_memory_layout(factor: int) -> None:
    """The preparation's windows are column-major; every layout and every column alone give
    the numbers of scipy.signal.decimate along time, bit for bit."""
    sps = pytest.importorskip("scipy.signal")
    rng = np.random.default_rng(5)
    x = rng.normal(size=(4000, 5)).cumsum(axis=0)
    expect = x
    for q in decimation_stages(factor):
        ftype = "iir" if q <= dec.MAX_STAGE else "fir"
        expect = sps.decimate(expect, q, ftype=ftype, axis=0, zero_phase=True)
    for layout in (x, np.asfortranarray(x), x[:, ::-1].copy()[:, ::-1]):
        np.testing.assert_array_equal(decimate_columns(layout, factor), expect)
        (got,) = parallel_decimate([layout], factor, 0)
        np.testing.assert_array_equal(got, expect)
    np.testing.assert_array_equal(decimate_columns(x[:, 2:3].copy(), factor), expect[:, 2:3])
