"""Signal processing of identification data (paper §2.2, model.md "Data processing").

Velocities and accelerations come from the measured positions by a zero-phase Butterworth
low-pass and central differences (Gautier's "derivative band-pass filtering"). The torque side
(current references) and every column of the observation matrix are then low-pass filtered and
down-sampled alike ("parallel decimation", :mod:`drivegain.identify.decimate`), which removes
the high-frequency content the rigid-body model does not explain while keeping ``Y = W χ``
exact (filtering is linear and the same on both sides). Finally the borders, where the
zero-phase filters start from padded data, are trimmed. This module chooses those filters
(:func:`default_filter`: cut-offs, decimation factor, trim) and differentiates the positions.

All time series have time along axis 0; rates are in Hz.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivegain.errors import DataError, InputError, UsageError
from drivegain.identify.coulombsign import SIGN_QUANTUM_NOISE
from drivegain.identify.decimate import (
    DECIMATE_IIR_ORDER,
    MAX_STAGE,
    check_finite,
    decimation_stages,
)
from drivegain.scipyimport import import_scipy

# scipy.signal without its import-time docstring rewriting (most of its import time)
sps = import_scipy("scipy.signal")

#: multiple of the trajectory's highest harmonic used as the position cut-off
BANDWIDTH_MULTIPLE = 10.0
#: cut-off when the trajectory's bandwidth is unknown: rate / 20 (so that the central
#: differences are accurate to about 1 % even at the cut-off), at most this, Hz
MAX_DEFAULT_CUTOFF_HZ = 50.0
#: multiple of the position cut-off used as the Coulomb sign's (FilterSettings.sign_cutoff_hz):
#: 8 measured better than 4 on the simulated cell's closed-loop runs (docs/model.md)
SIGN_CUTOFF_MULTIPLE = 8.0
#: the sign's default cut-off stays below this fraction of the sample rate (Nyquist: 0.5)
SIGN_CUTOFF_RATE_FRACTION = 0.4
#: longest taper of the reversal mask, s: a joint of an excitation reverses every second or so,
#: so a wider one would leave little of a run
MAX_REVERSAL_MASK_S = 1.0
# Relative level below which a filter's impulse response counts as settled (border trimming).
# filtfilt starts from the steady state of an odd extension, so the actual border error is far
# below the impulse response's envelope: with 1e-3 here, the trimmed interior matches the
# processing of a much longer record to about 1e-4 (tests/identify_data/test_signal.py).
_SETTLED = 1e-3


@dataclass(frozen=True, kw_only=True)
class FilterSettings:
    """How positions are filtered and the data decimated.

    Attributes
    ----------
    cutoff_hz
        Cut-off frequency of the zero-phase Butterworth low-pass on positions, Hz.
    order
        Order of that Butterworth filter (the forward-backward pass doubles it).
    decimate
        Decimation factor (1: no decimation).
    trim
        Samples dropped at each border after decimation (filter transients).
    current_delay
        Age of each current sample relative to its position sample, in samples (0 to 1): the
        current recorded at t_k stands for the torque at t_k − current_delay/rate. 0.5 for
        drives that report the current averaged over the period ending at the sample (the
        simulated drives do); the currents are interpolated onto the position samples.
    sign_cutoff_hz
        Cut-off of the low-pass whose velocity gives the Coulomb friction columns their sign,
        Hz; None: ``cutoff_hz``. Only the sign's zero crossings matter there, and a drive's
        loop moves them by tens of ms at each reversal (dwell, then breakaway): a cut-off a few
        times ``cutoff_hz`` keeps their timing where the heavier filter of the other columns
        shifts it (docs/model.md, "Where the Coulomb sign comes from").
    sign_noise_limit
        When set, the preparation lowers ``sign_cutoff_hz`` by octaves (not below
        ``cutoff_hz``) until each drive's encoder quantum adds at most this fraction of its RMS
        speed to that velocity (:mod:`~drivegain.identify.coulombsign`); None: as given.
    reversal_mask_s
        When set (``--reversal-mask``), the equations of each coupled group of drives are
        weighted out of every fit near its reversals, before the decimation: 0 inside the
        zones, rising over this many seconds either side
        (:func:`~drivegain.identify.reversals.reversal_mask`); None: every equation counts.
    reversal_mask_drives
        With ``reversal_mask_s``: the drives (from 0) whose coupled groups get the mask
        (``--reversal-mask auto`` chooses them); None: every group.
    """

    cutoff_hz: float
    order: int = 4
    decimate: int
    trim: int
    current_delay: float = 0.0
    sign_cutoff_hz: float | None = None
    sign_noise_limit: float | None = None
    reversal_mask_s: float | None = None
    reversal_mask_drives: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.cutoff_hz) and self.cutoff_hz > 0):
            raise InputError(f"must be a positive number of Hz, got {self.cutoff_hz}", key="cutoff")
        if isinstance(self.order, bool) or not isinstance(self.order, int) or self.order < 1:
            raise InputError(f"must be an integer >= 1, got {self.order!r}", key="order")
        if isinstance(self.decimate, bool) or not isinstance(self.decimate, int):
            raise InputError(f"must be an integer >= 1, got {self.decimate!r}", key="decimate")
        if self.decimate < 1:
            raise InputError(f"must be an integer >= 1, got {self.decimate}", key="decimate")
        if isinstance(self.trim, bool) or not isinstance(self.trim, int) or self.trim < 0:
            raise InputError(f"must be an integer >= 0, got {self.trim!r}", key="trim")
        if not (math.isfinite(self.current_delay) and 0.0 <= self.current_delay <= 1.0):
            raise InputError(
                f"must be between 0 and 1 sample, got {self.current_delay}", key="current_delay"
            )
        sc = self.sign_cutoff_hz
        if sc is not None and not (math.isfinite(sc) and sc > 0):
            raise InputError(f"must be a positive number of Hz, got {sc}", key="sign_cutoff")
        lim = self.sign_noise_limit
        if lim is not None and not (math.isfinite(lim) and lim > 0):
            raise InputError(f"must be a positive fraction, got {lim}", key="sign_noise_limit")
        check_reversal_mask(self.reversal_mask_s)
        drives = self.reversal_mask_drives
        if drives is not None:
            if self.reversal_mask_s is None:
                raise InputError("needs reversal_mask (a taper)", key="reversal_mask_drives")
            if (
                not isinstance(drives, tuple)
                or not drives
                or any(isinstance(d, bool) or not isinstance(d, int) or d < 0 for d in drives)
                or list(drives) != sorted(set(drives))
            ):
                raise InputError(
                    f"must be increasing drive indices from 0, got {drives!r}",
                    key="reversal_mask_drives",
                )

    @property
    def sign_cutoff(self) -> float:
        """Cut-off of the velocity that signs the Coulomb columns, Hz."""
        return self.cutoff_hz if self.sign_cutoff_hz is None else self.sign_cutoff_hz

    def output_rate(self, rate_hz: float) -> float:
        """Sample rate after decimation, Hz."""
        return rate_hz / self.decimate


def check_reversal_mask(taper_s: float | None, key: str = "reversal_mask") -> None:
    """Refuse a reversal mask's taper outside (0, :data:`MAX_REVERSAL_MASK_S`] s (None: no mask).

    Raises
    ------
    InputError
        Naming ``key``.
    """
    if taper_s is not None and not (
        math.isfinite(taper_s) and 0.0 < taper_s <= MAX_REVERSAL_MASK_S
    ):
        raise InputError(
            f"must be a positive number of seconds, at most {MAX_REVERSAL_MASK_S:g}, got {taper_s}",
            key=key,
        )


def _check_rate(rate_hz: float) -> None:
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise InputError(f"must be a positive number of Hz, got {rate_hz}", key="rate")


def _check_cutoff(cutoff_hz: float, rate_hz: float, key: str = "cutoff") -> None:
    if not (math.isfinite(cutoff_hz) and 0 < cutoff_hz < rate_hz / 2):
        raise InputError(
            f"cut-off {cutoff_hz} Hz must be between 0 and the Nyquist frequency "
            f"{rate_hz / 2:g} Hz (sample rate {rate_hz:g} Hz)",
            key=key,
        )


def _smooth_at_most(bound: int) -> int:
    """Largest integer <= bound whose prime factors are all <= 7 (cheap to decimate in stages)."""
    for m in range(max(bound, 1), 0, -1):
        r = m
        for p in (2, 3, 5, 7):
            while r % p == 0:
                r //= p
        if r == 1:
            return m
    return 1


def _settling_samples(sos: np.ndarray, cutoff_fraction: float) -> int:
    """Samples until a filter's impulse response stays below :data:`_SETTLED` of its peak."""
    length = int(60.0 / cutoff_fraction) + 64
    impulse = np.zeros(length)
    impulse[0] = 1.0
    h = np.abs(sps.sosfilt(sos, impulse))
    above = np.flatnonzero(h > _SETTLED * h.max())
    return int(above[-1]) + 1 if above.size else 1


def _decimation_sos(q: int) -> np.ndarray:
    # The filter scipy.signal.decimate uses for ftype="iir".
    return np.asarray(sps.cheby1(DECIMATE_IIR_ORDER, 0.05, 0.8 / q, output="sos"))


def _trim_for(rate_hz: float, cutoff_hz: float, order: int, factor: int) -> int:
    """Decimated samples to drop at each border so that filter transients have died out."""
    sos = np.asarray(sps.butter(order, cutoff_hz, fs=rate_hz, output="sos"))
    # Transients of the position filter, in input samples (+2 for the difference stencils).
    span = float(_settling_samples(sos, 2 * cutoff_hz / rate_hz) + 2)
    step = 1
    for q in decimation_stages(factor):
        if q <= MAX_STAGE:
            span += _settling_samples(_decimation_sos(q), 0.8 / q) * step
        else:
            span += 20 * q * step  # half the length of decimate's FIR filter
        step *= q
    return math.ceil(span / factor) + 1


def default_filter(
    rate_hz: float,
    bandwidth_hz: float | None = None,
    *,
    cutoff_hz: float | None = None,
    decimate: int | None = None,
    order: int = 4,
    current_delay: float = 0.0,
    sign_cutoff_hz: float | None = None,
    reversal_mask_s: float | None = None,
    reversal_mask_drives: tuple[int, ...] | None = None,
) -> FilterSettings:
    """Filter settings derived from the sample rate and the trajectory's bandwidth.

    Cut-off: :data:`BANDWIDTH_MULTIPLE` times the trajectory's highest harmonic when it is known,
    else rate/20; in both cases at most rate/20 and :data:`MAX_DEFAULT_CUTOFF_HZ` (the rigid-body
    dynamics of an arm lie well below 50 Hz, the rest is noise). Decimation: the largest factor
    whose anti-aliasing filter (0.8 × the new Nyquist frequency) still passes the cut-off.
    Trim: from the impulse responses of the filters actually used.

    Parameters
    ----------
    rate_hz
        Sample rate of the data, Hz.
    bandwidth_hz
        Highest frequency of the excitation trajectory (its highest harmonic), Hz, if known.
    cutoff_hz, decimate
        Overrides (``--cutoff``, ``--decimate``); the trim is derived for them.
    order
        Butterworth order.
    current_delay
        Age of the current samples, samples (:class:`FilterSettings`).
    sign_cutoff_hz
        Cut-off of the velocity that signs the Coulomb columns (``--sign-cutoff``), Hz, below
        the Nyquist frequency; None: :data:`SIGN_CUTOFF_MULTIPLE` times the position cut-off,
        at most :data:`SIGN_CUTOFF_RATE_FRACTION` of the rate (never below the cut-off), lowered
        where the encoder is coarse (``sign_noise_limit`` :data:`SIGN_QUANTUM_NOISE`).
    reversal_mask_s, reversal_mask_drives
        Taper of the reversal mask, s, and the drives it weighs (:class:`FilterSettings`);
        None: no mask, every group.

    Raises
    ------
    InputError
        Rate, bandwidth, cut-off or factor out of range, or a rate too low for the bandwidth.
    """
    _check_rate(rate_hz)
    if bandwidth_hz is not None and not (math.isfinite(bandwidth_hz) and bandwidth_hz > 0):
        raise InputError(f"must be a positive number of Hz, got {bandwidth_hz}", key="bandwidth")
    cap = min(rate_hz / 20.0, MAX_DEFAULT_CUTOFF_HZ)
    if cutoff_hz is None:
        cutoff_hz = cap if bandwidth_hz is None else min(BANDWIDTH_MULTIPLE * bandwidth_hz, cap)
        if bandwidth_hz is not None and cutoff_hz < 2 * bandwidth_hz:
            raise InputError(
                f"sample rate {rate_hz:g} Hz is too low for a trajectory with harmonics up to "
                f"{bandwidth_hz:g} Hz (needs at least {40 * bandwidth_hz:g} Hz, or give --cutoff)",
                key="rate",
            )
    _check_cutoff(cutoff_hz, rate_hz)
    if bandwidth_hz is not None and cutoff_hz <= bandwidth_hz:
        raise InputError(
            f"cut-off {cutoff_hz:g} Hz would remove the trajectory's harmonics up to "
            f"{bandwidth_hz:g} Hz",
            key="cutoff",
        )
    if decimate is None:
        decimate = _smooth_at_most(int(0.4 * rate_hz / cutoff_hz))
    elif isinstance(decimate, bool) or not isinstance(decimate, int) or decimate < 1:
        raise InputError(f"must be an integer >= 1, got {decimate!r}", key="decimate")
    kept = 0.4 * rate_hz / decimate  # pass band of the decimation filter
    if bandwidth_hz is not None and decimate > 1 and kept <= bandwidth_hz:
        raise InputError(
            f"decimation by {decimate} keeps only up to {kept:g} Hz, below the trajectory's "
            f"harmonics up to {bandwidth_hz:g} Hz",
            key="decimate",
        )
    if isinstance(order, bool) or not isinstance(order, int) or order < 1:
        raise InputError(f"must be an integer >= 1, got {order!r}", key="order")
    noise_limit = None  # a cut-off given by hand is used as given
    if sign_cutoff_hz is None:
        noise_limit = SIGN_QUANTUM_NOISE
        sign_cutoff_hz = max(
            cutoff_hz, min(SIGN_CUTOFF_MULTIPLE * cutoff_hz, SIGN_CUTOFF_RATE_FRACTION * rate_hz)
        )
    _check_cutoff(sign_cutoff_hz, rate_hz, key="sign_cutoff")
    # The slower filter of the two sets the trim (a sign cut-off above the position's settles
    # sooner; one below it, given by hand, later).
    trim = _trim_for(rate_hz, min(cutoff_hz, sign_cutoff_hz), order, decimate)
    return FilterSettings(
        cutoff_hz=float(cutoff_hz),
        order=order,
        decimate=decimate,
        trim=trim,
        current_delay=float(current_delay),
        sign_cutoff_hz=float(sign_cutoff_hz),
        sign_noise_limit=noise_limit,
        reversal_mask_s=None if reversal_mask_s is None else float(reversal_mask_s),
        reversal_mask_drives=reversal_mask_drives,
    )


def derivatives(
    q: np.ndarray,
    rate_hz: float,
    settings: FilterSettings,
    *,
    source: str | Path | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Filtered positions, velocities and accelerations from sampled positions.

    Zero-phase Butterworth low-pass (:func:`scipy.signal.sosfiltfilt`), then central differences
    ``(q[k+1] - q[k-1]) / 2h`` and ``(q[k+1] - 2 q[k] + q[k-1]) / h²``. The first and last
    samples use one-sided values; they lie in the border that
    :func:`~.decimate.parallel_decimate` trims.

    Parameters
    ----------
    q
        Positions, rad, shape (N,) or (N, n).
    rate_hz
        Sample rate, Hz.
    settings
        Cut-off and order of the low-pass.
    source
        File the data came from, named in errors.

    Returns
    -------
    tuple of numpy.ndarray
        ``q_f`` (rad), ``qd`` (rad/s), ``qdd`` (rad/s²), each shaped like ``q``.

    Raises
    ------
    DataError
        NaN/inf in ``q`` or too few samples for the filter.
    InputError
        Bad rate or a cut-off at or above the Nyquist frequency.
    """
    _check_rate(rate_hz)
    _check_cutoff(settings.cutoff_hz, rate_hz)
    x = np.asarray(q, dtype=float)
    if x.ndim not in (1, 2):
        # Programming error of the caller (the log reader always gives (N, n)): not user data.
        raise UsageError(f"positions must have shape (N,) or (N, n), got {x.shape}")
    sos = np.asarray(sps.butter(settings.order, settings.cutoff_hz, fs=rate_hz, output="sos"))
    padlen = 3 * (2 * len(sos) + 1)  # sosfiltfilt's default padding
    if x.shape[0] <= padlen:
        raise DataError(
            f"too few samples for the position filter: {x.shape[0]}, the order-{settings.order} "
            f"Butterworth needs more than {padlen}",
            file=source,
        )
    check_finite(x, "position", source)
    qf = sps.sosfiltfilt(sos, x, axis=0)
    h = 1.0 / rate_hz
    qd = np.empty_like(qf)
    qd[1:-1] = (qf[2:] - qf[:-2]) / (2 * h)
    qd[0] = (qf[1] - qf[0]) / h
    qd[-1] = (qf[-1] - qf[-2]) / h
    qdd = np.empty_like(qf)
    qdd[1:-1] = (qf[2:] - 2 * qf[1:-1] + qf[:-2]) / (h * h)
    qdd[0] = qdd[1]
    qdd[-1] = qdd[-2]
    return qf, qd, qdd
