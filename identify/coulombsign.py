"""How far the Coulomb sign's velocity may be filtered less than the other columns' (its cut-off).

The Coulomb columns take the sign of a velocity filtered at a higher cut-off than the position's
(:attr:`~drivegain.identify.signal.FilterSettings.sign_cutoff_hz`), which keeps the sign's zero
crossings on a closed-loop drive's reversals. The price is the encoder's quantum: its noise on a
velocity grows about as the cut-off to the power 1.5, and where it is a fair share of the
speeds a joint passes through near its reversals the sign flickers and its timing jitters. On
the validation study's exact tracking with a coarse 1e-3° joint quantum, 8 times the position
cut-off tripled the gain errors of random excitations (0.21 → 0.64 % RMS over 100 seeds), for
nothing in return; the cell's motor encoders are fine enough that the same cut-off costs
nothing and nearly halves the closed-loop error (docs/model.md, "Where the Coulomb sign comes
from").

So the sign's cut-off is lowered by octaves, not below the position cut-off, until the
quantisation noise of every drive's encoder on that velocity is a small fraction
(:data:`SIGN_QUANTUM_NOISE`) of the drive's RMS speed. The encoder step is read from the data
(the lattice its position changes sit on, per drive), the noise gain of the filter and
the five-point difference is computed from their frequency responses. Plain functions.
"""

from __future__ import annotations

import math

import numpy as np

from drivegain.errors import InputError
from drivegain.scipyimport import import_scipy

sps = import_scipy("scipy.signal")

#: Largest quantisation noise on the sign's velocity, as a fraction of each drive's RMS speed,
#: at which a cut-off is kept. Measured at 8 times the position cut-off (docs/model.md): the
#: simulated cell's motor encoders 0.001-0.02 %, the real TX-40 recording 0.003 %, the study's
#: exact tracking with a 1e-3° joint quantum 0.05-0.4 % on random excitations, where that
#: cut-off cost accuracy (at 2 times the position cut-off: 0.006-0.05 %).
SIGN_QUANTUM_NOISE = 5e-4
# Position changes below this many radians are taken as float rounding, not an encoder step
# (a coupled joint's position is computed from motor counts).
_ROUNDING_RAD = 1e-12
# A lattice of encoder steps (encoder_steps): the share of the changes of up to _LATTICE_SPAN
# steps that lie within _LATTICE_TOLERANCE steps of a whole number of them. Unquantised
# changes put about 2 × tolerance of them there.
_LATTICE_SPAN = 20.0
_LATTICE_TOLERANCE = 0.02
_LATTICE_SHARE = 0.9
# Frequency points of the noise-gain integral (the integrand is smooth: 1e-6 relative error).
_POINTS = 4096


def encoder_steps(positions: np.ndarray) -> np.ndarray:
    """Encoder step of each column of sampled positions, where they show one, (n,).

    Quantised positions change by whole steps: the changes between consecutive samples sit on
    a lattice. The step is the smallest change, or a fraction 1/2-1/4 of it (a drive too fast
    to ever move by a single step between samples), whichever first puts
    :data:`_LATTICE_SHARE` of the changes up to :data:`_LATTICE_SPAN` steps within
    :data:`_LATTICE_TOLERANCE` of the lattice. Positions that sit on no lattice (unquantised,
    or an encoder finer than the least motion between samples) give 0: no quantum shows.

    Parameters
    ----------
    positions
        Sampled positions, rad, (N, n).

    Returns
    -------
    numpy.ndarray
        Step per column, rad; 0 where none shows or the column never changes.
    """
    x = np.asarray(positions, dtype=float)
    if x.ndim != 2:
        raise ValueError(f"positions must be (N, n), got shape {x.shape}")
    steps = np.zeros(x.shape[1])
    for j in range(x.shape[1]):
        d = np.abs(np.diff(x[:, j]))
        d = d[d > _ROUNDING_RAD]
        if d.size == 0:
            continue
        for parts in range(1, 5):
            step = d.min() / parts
            r = d[d <= _LATTICE_SPAN * step] / step
            if np.mean(np.abs(r - np.rint(r)) <= _LATTICE_TOLERANCE) >= _LATTICE_SHARE:
                steps[j] = step
                break
    return steps


def velocity_noise_gain(rate_hz: float, cutoff_hz: float, order: int) -> float:
    """RMS velocity per RMS of white position noise through the velocity's filters, 1/s.

    The zero-phase Butterworth (:func:`scipy.signal.sosfiltfilt`, so its magnitude squared)
    followed by the five-point central difference of
    :func:`~drivegain.identify.prepare.five_point`.

    Parameters
    ----------
    rate_hz
        Sample rate, Hz.
    cutoff_hz
        Cut-off of the low-pass, Hz, below the Nyquist frequency.
    order
        Butterworth order.
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0 and 0 < cutoff_hz < rate_hz / 2):
        raise InputError(
            f"cut-off {cutoff_hz} Hz must lie between 0 and half the rate {rate_hz} Hz",
            key="sign_cutoff",
        )
    sos = sps.butter(order, cutoff_hz, fs=rate_hz, output="sos")
    w = np.linspace(0.0, np.pi, _POINTS)  # rad/sample
    _, h = sps.sosfreqz(sos, worN=w)
    # five-point difference (a − 8b + 8d − e)/12h: magnitude (8 sin ω − sin 2ω)/6h
    d = (8.0 * np.sin(w) - np.sin(2.0 * w)) / 6.0 * rate_hz
    power = np.abs(h) ** 4 * d**2
    area = float(np.sum(power[1:] + power[:-1])) * (w[1] - w[0]) / 2.0  # trapezoids
    return math.sqrt(area / np.pi)


def quantum_noise(
    steps: np.ndarray, speed_rms: np.ndarray, rate_hz: float, cutoff_hz: float, order: int
) -> np.ndarray:
    """Quantisation noise on each drive's velocity at ``cutoff_hz``, per its RMS speed, (n,).

    Parameters
    ----------
    steps
        Encoder step of each drive, rad (:func:`encoder_steps`); the quantisation error is
        taken as uniform over a step (variance step²/12).
    speed_rms
        RMS speed of each drive, rad/s; a drive that does not move counts as noise-free.
    rate_hz, cutoff_hz, order
        The velocity's sampling and filter (:func:`velocity_noise_gain`).
    """
    gain = velocity_noise_gain(rate_hz, cutoff_hz, order)
    noise = gain * np.asarray(steps, dtype=float) / math.sqrt(12.0)
    speed = np.asarray(speed_rms, dtype=float)
    return np.divide(noise, speed, out=np.zeros_like(noise), where=speed > 0)


def sign_cutoff(
    ceiling_hz: float,
    floor_hz: float,
    rate_hz: float,
    order: int,
    steps: np.ndarray,
    speed_rms: np.ndarray,
    limit: float = SIGN_QUANTUM_NOISE,
) -> float:
    """The sign's cut-off: ``ceiling_hz`` halved until every drive's quantum noise is within
    ``limit`` (:func:`quantum_noise`), never below ``floor_hz`` (the position cut-off).

    Parameters
    ----------
    ceiling_hz, floor_hz
        Highest and lowest cut-offs, Hz.
    rate_hz, order
        Sample rate (Hz) and Butterworth order.
    steps, speed_rms
        Encoder step (rad) and RMS speed (rad/s) of each drive.
    limit
        Largest noise per RMS speed kept (> 0).

    Returns
    -------
    float
        Cut-off, Hz: ``ceiling_hz / 2**k`` for the smallest such k, or ``floor_hz``.
    """
    if not (math.isfinite(limit) and limit > 0):
        raise InputError(f"must be a positive fraction, got {limit}", key="sign_noise_limit")
    hz = ceiling_hz
    while hz > floor_hz:
        if np.all(quantum_noise(steps, speed_rms, rate_hz, hz, order) <= limit):
            return float(hz)
        hz /= 2.0
    return float(floor_hz)
