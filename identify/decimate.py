"""Parallel decimation: the same low-pass and down-sampling on the torques and every column of
the observation matrix (paper §2.2, model.md "Data processing").

:func:`scipy.signal.decimate`'s zero-phase Chebyshev I filter, in stages for large factors, with
its filter designed once per factor; columns that repeat another are filtered once
(:func:`decimate_columns`), long records in windows that overlap by the filter's memory
(:func:`decimation_windows`, :func:`decimation_memory`). Filtering is linear and the same on
both sides of ``Y = W χ``, so the decimated equations stay exact.

All time series have time along axis 0.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from drivegain.errors import DataError, InputError, UsageError
from drivegain.scipyimport import import_scipy

# scipy.signal without its import-time docstring rewriting (most of its import time)
sps = import_scipy("scipy.signal")

#: order of the Chebyshev I low-pass :func:`scipy.signal.decimate` applies (its default)
DECIMATE_IIR_ORDER = 8
#: largest factor one IIR decimation stage takes (SciPy advises several calls beyond 13)
MAX_STAGE = 13
# Columns filtered at a time by parallel_decimate (bounds the temporaries of filtfilt).
_COLUMN_BLOCK = 256


def decimation_stages(factor: int) -> list[int]:
    """Split a decimation factor into stages of at most :data:`MAX_STAGE` where possible.

    A prime factor above :data:`MAX_STAGE` becomes its own stage (filtered by a FIR filter, see
    :func:`parallel_decimate`).
    """
    primes: list[int] = []
    r, p = factor, 2
    while p * p <= r:
        while r % p == 0:
            primes.append(p)
            r //= p
        p += 1
    if r > 1:
        primes.append(r)
    stages: list[int] = []
    for f in sorted(primes, reverse=True):
        for i, s in enumerate(stages):
            if s * f <= 10:  # 10, not 13: a margin on the IIR filter's conditioning
                stages[i] = s * f
                break
        else:
            stages.append(f)
    return sorted(stages, reverse=True)


def check_finite(x: np.ndarray, what: str, source: str | Path | None) -> None:
    """Raise :class:`DataError` naming the first sample of ``x`` (time along axis 0) that is
    NaN or inf."""
    finite = np.isfinite(x)
    if not finite.all():
        k = int(np.argwhere(~finite)[0][0])
        raise DataError(f"{what} is not finite (NaN or inf) at sample {k}", file=source)


@functools.lru_cache(maxsize=32)
def _stage_sos(q: int) -> np.ndarray:
    # What scipy.signal.decimate builds for ftype="iir" (Chebyshev I via zpk → sos), designed
    # once per factor: the chunked preparation decimates thousands of blocks.
    z, p, k = sps.cheby1(DECIMATE_IIR_ORDER, 0.05, 0.8 / q, output="zpk")
    sos = np.asarray(sps.zpk2sos(z, p, k), dtype=float)
    sos.setflags(write=False)
    return sos


def _decimate_stage(x: np.ndarray, q: int) -> np.ndarray:
    # Filtered along the last axis of x.T: SciPy's filters copy their input with that axis
    # last and contiguous, which for a column-major x (the preparation's windows) is a plain
    # copy instead of a transposition. Each column is filtered alone, so the numbers are the
    # same either way.
    if q <= MAX_STAGE:
        # scipy.signal.decimate(x, q, ftype="iir", zero_phase=True) without its filter design
        return np.asarray(sps.sosfiltfilt(_stage_sos(q).copy(), x.T, axis=-1)[..., ::q].T)
    return np.asarray(sps.decimate(x.T, q, ftype="fir", axis=-1, zero_phase=True).T)


def decimated_length(n_samples: int, factor: int) -> int:
    """Samples left after decimating ``n_samples`` by ``factor`` (before trimming)."""
    n = n_samples
    for q in decimation_stages(factor):
        n = -(-n // q)
    return n


def parallel_decimate(
    arrays: Sequence[np.ndarray],
    factor: int,
    trim: int,
    *,
    source: str | Path | None = None,
) -> list[np.ndarray]:
    """Low-pass, down-sample and trim several arrays with the same filter on every column.

    Decimation is :func:`scipy.signal.decimate` (Chebyshev I, order 8, zero phase), in stages
    of at most 10 for large factors; a prime factor above 13 gets decimate's FIR filter.

    Parameters
    ----------
    arrays
        Arrays with time along axis 0 and the same number of samples, any trailing shape
        (torques (N, n), regressors (N, n, p), ...).
    factor
        Decimation factor (1: trimming only).
    trim
        Samples dropped at each border after decimation.
    source
        File the data came from, named in errors.

    Returns
    -------
    list of numpy.ndarray
        The decimated and trimmed arrays, same trailing shapes.

    Raises
    ------
    DataError
        NaN/inf, or too few samples for the decimation filter or for the trim.
    InputError
        ``factor`` < 1 or ``trim`` < 0.
    """
    if isinstance(factor, bool) or not isinstance(factor, int | np.integer) or factor < 1:
        raise InputError(f"must be an integer >= 1, got {factor!r}", key="decimate")
    if isinstance(trim, bool) or not isinstance(trim, int | np.integer) or trim < 0:
        raise InputError(f"must be an integer >= 0, got {trim!r}", key="trim")
    xs = [np.asarray(a, dtype=float) for a in arrays]
    if not xs:
        return []
    n_samples = xs[0].shape[0]
    for i, x in enumerate(xs):
        if x.ndim == 0 or x.shape[0] != n_samples:
            # Programming error of the caller (every array comes from the same recording).
            raise UsageError(f"array {i} has shape {x.shape}, expected {n_samples} samples first")
    stages = decimation_stages(int(factor))
    n = n_samples
    padlen = 3 * (2 * (DECIMATE_IIR_ORDER // 2) + 1)  # filtfilt padding of decimate's IIR
    for q in stages:
        need = padlen if q <= MAX_STAGE else 2 * (20 * q + 1)
        if n <= need:
            raise DataError(
                f"too few samples to decimate by {factor}: {n_samples} samples, the stage by "
                f"{q} needs more than {need} at its input",
                file=source,
            )
        n = -(-n // q)
    if n <= 2 * trim:
        raise DataError(
            f"too few samples: {n_samples} samples decimated by {factor} leave {n}, not more "
            f"than the {2 * trim} border samples to trim",
            file=source,
        )
    out = []
    for i, x in enumerate(xs):
        flat = x.reshape(n_samples, -1)
        res = np.empty((n, flat.shape[1]))
        for c0 in range(0, flat.shape[1], _COLUMN_BLOCK):
            block = flat[:, c0 : c0 + _COLUMN_BLOCK]
            for q in stages:
                block = _decimate_stage(block, q)
            res[:, c0 : c0 + _COLUMN_BLOCK] = block
        # A NaN or inf in a column reaches every later output sample of the forward pass and
        # then, backwards, every sample (IIR) or a stretch of at least 20 (FIR): checking the
        # output, a factor smaller, finds it; the input is searched only then, for the
        # sample to name.
        if not np.isfinite(res).all():
            check_finite(x, f"array {i}", source)
        out.append(res[trim : n - trim].reshape((n - 2 * trim, *x.shape[1:])))
    return out


#: Columns filtered per call by :func:`decimate_columns` (bounds the filter's temporaries).
SERIES_BLOCK = 48


def first_equal(values: np.ndarray) -> np.ndarray:
    """For each column of ``values`` (samples, columns), the index of the first column equal
    to it, bit for bit (its own index when no earlier one is).

    Meant for sample values of regressor series at random states: equal there, two series are
    candidates for :func:`decimate_columns` to filter once (it compares them again).
    """
    out = np.arange(values.shape[1])
    seen: dict[bytes, int] = {}
    for k in range(values.shape[1]):
        out[k] = seen.setdefault(np.ascontiguousarray(values[:, k]).tobytes(), k)
    return out


def decimate_columns(
    x: np.ndarray,
    factor: int,
    same_as: np.ndarray | None = None,
    *,
    source: str | Path | None = None,
) -> np.ndarray:
    """:func:`parallel_decimate` of the columns of ``x`` (samples, columns), untrimmed, each
    group of equal columns filtered once.

    Why: about a sixth of a robot's regressor series repeat another one (the same product of
    velocities in two parameters' columns), and filtering is most of a run's preparation.

    Parameters
    ----------
    x
        Samples along axis 0, (samples, columns); any unit.
    factor
        Decimation factor.
    same_as
        Per column, an earlier column it may equal (:func:`first_equal`; None: none). Column
        k is filtered unless ``x[:, k]`` equals ``x[:, same_as[k]]`` here, bit for bit, and
        that one is filtered itself; then it gets that column's decimated samples, the very
        numbers its own filtering gives (the filter acts on each column alone).
    source
        File the data came from, named in errors.

    Returns
    -------
    numpy.ndarray
        (:func:`decimated_length` of the samples, columns), in ``x``'s unit.

    Raises
    ------
    DataError
        As :func:`parallel_decimate`.
    """
    k = x.shape[1]
    own = np.arange(k)
    src = own if same_as is None else np.asarray(same_as, dtype=np.intp)
    shared = np.zeros(k, dtype=bool)
    cand = np.flatnonzero((src != own) & (src[src] == src))
    if cand.size:
        shared[cand] = np.all(x[:, cand] == x[:, src[cand]], axis=0)
    todo = np.flatnonzero(~shared)
    out = np.empty((decimated_length(x.shape[0], factor), k))
    # Columns to filter that lie side by side (a caller may put the repeats last) are taken
    # as slices of x, without a gathered copy.
    side_by_side = todo.size > 0 and todo[-1] - todo[0] + 1 == todo.size
    for g in range(0, todo.size, SERIES_BLOCK):
        picked = todo[g : g + SERIES_BLOCK]
        sel: slice | np.ndarray = picked
        if side_by_side:
            sel = slice(int(picked[0]), int(picked[0]) + picked.size)
        (out[:, sel],) = parallel_decimate([x[:, sel]], factor, 0, source=source)
    out[:, shared] = out[:, src[shared]]
    return out


def decimation_windows(n: int, factor: int, size: int) -> list[tuple[int, int]]:
    """Boundaries of about ``size`` samples each, on multiples of ``factor`` (so the decimated
    samples of the windows line up), covering ``n`` samples."""
    size = max(factor, (size // factor) * factor)
    count = max(1, math.ceil(n / size))
    bounds = [min(n, round(i * n / count / factor) * factor) for i in range(count)] + [n]
    return [(a, b) for a, b in itertools.pairwise(bounds) if b > a]


@functools.cache
def decimation_memory(factor: int, tol: float = 1e-11) -> int:
    """Input samples over which :func:`parallel_decimate`'s filter remembers, to ``tol``.

    Measured on the filter itself: the (zero-phase, symmetric) response to an impulse, out to
    where it stays below ``tol`` of its peak. Chunks that overlap by this much give the same
    decimated samples as the whole signal, to ``tol`` relative.
    """
    if factor == 1:
        return 0
    length = 1000 * factor
    while True:
        x = np.zeros((length, 1))
        x[length // 2] = 1.0
        (y,) = parallel_decimate([x], factor, 0)
        h = np.abs(y[:, 0])
        centre = int(np.argmax(h))
        above = np.flatnonzero(h > tol * h[centre])
        reach = int(max(centre - above[0], above[-1] - centre))
        if reach < len(h) // 4:
            return (reach + 2) * factor
        length *= 4
