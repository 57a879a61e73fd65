"""Joint limits for excitation: the margins we keep, sample checks and rigorous Fourier bounds.

Two sets of limits are in play. The robot file's limits are hard: every sample of every motion
must respect them (:func:`check_limits`). The excitation and the ruckig segments are planned
inside tighter *working* limits (:class:`ExcitationLimits`): position ranges shrunk by a margin,
velocity, acceleration and jerk limits scaled by a fraction, which leaves room for the tracking
error of the drives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivegain.config.robot import Robot
from drivegain.errors import TrajectoryError
from drivegain.formats.fourier import FourierTrajectory, basis, derivative_bounds
from drivegain.formats.trajectory import ExcitationLimits

#: Relative tolerance of the sample checks (ruckig reaches its limits to round-off).
TOLERANCE = 1e-9

#: Most work of one :func:`fourier_usage` (grid points times 1 + 2H basis columns): about a
#: second on a busy machine. The default grid (1 ms) of a 10 s period stays within it up to 90
#: harmonics; a longer period or more harmonics gets a coarser grid.
USAGE_BUDGET = 2_000_000
#: Grid points evaluated at once by :func:`fourier_usage` (bounds its memory).
USAGE_BLOCK = 20_000

QUANTITIES = ("position", "velocity", "acceleration", "jerk")
UNITS = ("rad", "rad/s", "rad/s²", "rad/s³")


def check_limits(
    robot: Robot,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    qddd: np.ndarray | None = None,
    margin: float = 0.0,
    *,
    fraction: float = 1.0,
    label: str = "",
    times: np.ndarray | None = None,
) -> None:
    """Check samples against the robot's limits.

    Parameters
    ----------
    robot
        The robot (its limits are the reference).
    q, qd, qdd, qddd
        Samples (N, n): rad, rad/s, rad/s², rad/s³ (``qddd`` optional).
    margin
        Margin required from each position limit, rad.
    fraction
        Fraction of the velocity, acceleration and jerk limits allowed.
    label
        Prefix of the error message (e.g. ``"approach"``).
    times
        Times of the samples (s), to name the time of a violation.

    Raises
    ------
    TrajectoryError
        Naming the joint, the quantity, the value and the limit of the worst violation, or a
        non-finite sample.
    """
    names = robot.joint_names
    lo = robot.lower + margin
    hi = robot.upper - margin
    arrays = [q, qd, qdd] + ([] if qddd is None else [qddd])
    prefix = f"{label}: " if label else ""
    for k, x in enumerate(arrays):
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.shape[1] != robot.n:
            raise TrajectoryError(f"{prefix}{QUANTITIES[k]} samples have {x.shape[1]} joints")
        if not np.all(np.isfinite(x)):
            row, col = np.argwhere(~np.isfinite(x))[0]
            raise TrajectoryError(
                f"{prefix}{names[col]}: {QUANTITIES[k]} is not finite{_at(row, times)}"
            )
        if k == 0:
            tol = TOLERANCE * np.maximum(1.0, np.abs(hi - lo))
            over = np.maximum(x - (hi + tol), (lo - tol) - x)
            if np.any(over > 0.0):
                row, col = np.unravel_index(np.argmax(over), over.shape)
                raise TrajectoryError(
                    f"{prefix}{names[col]}: position {x[row, col]:.6g} rad is outside "
                    f"[{lo[col]:.6g}, {hi[col]:.6g}] rad{_at(int(row), times)}"
                )
        else:
            lim = (robot.velocity_limits, robot.acceleration_limits, robot.jerk_limits)[k - 1]
            lim = lim * fraction
            ratio = np.abs(x) / (lim * (1.0 + TOLERANCE))
            if np.any(ratio > 1.0):
                row, col = np.unravel_index(np.argmax(ratio), ratio.shape)
                raise TrajectoryError(
                    f"{prefix}{names[col]}: {QUANTITIES[k]} {x[row, col]:.6g} {UNITS[k]} exceeds "
                    f"the limit {lim[col]:.6g} {UNITS[k]}{_at(int(row), times)}"
                )


def _at(row: int, times: np.ndarray | None) -> str:
    return f" at t = {float(times[row]):.4f} s" if times is not None else f" (sample {row})"


@dataclass(frozen=True)
class FourierUsage:
    """How much of each working limit an excitation uses, bounded over continuous time.

    ``usage[k, j]`` (k = position, velocity, acceleration, jerk) is an upper bound of
    ``max_t |x| / limit`` for derivatives and of the position excursion from q0 relative to the
    room between q0 and the limit on that side; all of them scale linearly with the amplitudes,
    so dividing the amplitudes by ``usage.max()`` makes the series feasible (if q0 is inside).
    """

    usage: np.ndarray
    dt: float

    @property
    def worst(self) -> float:
        return float(self.usage.max())

    def worst_place(self) -> tuple[int, int]:
        """(quantity index, joint index) of the largest usage."""
        k, j = np.unravel_index(np.argmax(self.usage), self.usage.shape)
        return int(k), int(j)


def fourier_usage(
    fourier: FourierTrajectory, limits: ExcitationLimits, dt: float = 1e-3
) -> FourierUsage:
    """Rigorous limit usage of a periodic Fourier series.

    Each derivative is sampled over one period with step ``dt`` (coarser when that grid would
    exceed :data:`USAGE_BUDGET`); between samples the curve
    departs from the chord by at most dt²/8·sup|x''| (the linear interpolation error bound), with
    sup|x''| bounded analytically by :func:`~drivegain.formats.fourier.derivative_bounds`. So the
    sampled maximum plus that term bounds the true maximum over continuous time.

    Parameters
    ----------
    fourier
        The series.
    limits
        Working limits.
    dt
        Sampling step, s.
    """
    n_steps = max(2, int(np.ceil(fourier.period_s / dt)))
    # a long period on a fine grid would cost minutes: past the budget the step grows, and the
    # slack term (step² / 8 · sup|x''|) with it, so the bound stays rigorous, only less tight
    n_steps = min(n_steps, max(2, USAGE_BUDGET // (1 + 2 * fourier.harmonics)))
    step = fourier.period_s / n_steps
    theta = fourier.coefficients()
    bounds = derivative_bounds(fourier)
    usage = np.zeros((4, fourier.n))
    q0 = fourier.q0
    for k in range(4):
        hi = np.full(fourier.n, -np.inf)
        lo = np.full(fourier.n, np.inf)
        # both ends (the series is periodic), a block of times at a time (bounded memory)
        for start in range(0, n_steps + 1, USAGE_BLOCK):
            t = np.arange(start, min(n_steps + 1, start + USAGE_BLOCK)) * step
            x = basis(t, fourier.omega, fourier.harmonics, k) @ theta.T
            hi = np.maximum(hi, x.max(axis=0))
            lo = np.minimum(lo, x.min(axis=0))
        slack = step**2 / 8.0 * bounds[k + 2]
        hi = hi + slack
        lo = lo - slack
        if k == 0:
            room_hi = limits.upper - q0
            room_lo = q0 - limits.lower
            with np.errstate(divide="ignore", invalid="ignore"):
                u_hi = np.where(room_hi > 0, (hi - q0) / room_hi, np.inf)
                u_lo = np.where(room_lo > 0, (q0 - lo) / room_lo, np.inf)
            usage[0] = np.maximum(np.maximum(u_hi, u_lo), 0.0)
        else:
            usage[k] = np.maximum(hi, -lo) / limits.symmetric(k)
    return FourierUsage(usage=usage, dt=step)


def grid_constraints(
    t: np.ndarray, omega: float, harmonics: int, limits: ExcitationLimits
) -> tuple[np.ndarray, np.ndarray]:
    """Linear inequality constraints ``G @ theta <= h`` of the limits on a uniform time grid.

    ``theta`` is the flat coefficient vector, joint after joint ``[q0, a_1..a_H, b_1..b_H]``.
    Each limit is tightened by dt²/8 times a bound of the second derivative of the quantity
    (the most a curve can rise above its chord between two grid points): the acceleration limit
    for positions, the jerk limit for velocities, the jerk limit times ω_f·H for accelerations
    and times (ω_f·H)² for jerks; the last two hold for a series dominated by its top
    harmonic. The result is then verified rigorously by :func:`fourier_usage`.

    Parameters
    ----------
    t
        Uniform grid times, s (at least two).
    omega, harmonics
        Base angular frequency (rad/s) and number of harmonics.
    limits
        Working limits.

    Returns
    -------
    tuple of numpy.ndarray
        ``G`` (rows, n·(1 + 2H)) and ``h`` (rows,).
    """
    n = limits.n
    p = 1 + 2 * harmonics
    t = np.asarray(t, dtype=float)
    dt = float(t[1] - t[0])
    w_top = omega * harmonics
    curvature = [
        limits.acceleration,
        limits.jerk,
        limits.jerk * w_top,
        limits.jerk * w_top**2,
    ]
    blocks = [basis(t, omega, harmonics, k) for k in range(4)]
    m = t.shape[0]
    g = np.zeros((n * 4 * 2 * m, n * p))
    h = np.empty(n * 4 * 2 * m)
    row = 0
    for j in range(n):
        cols = slice(j * p, (j + 1) * p)
        for k, b in enumerate(blocks):
            slack = dt**2 / 8.0 * curvature[k][j]
            if k == 0:
                hi, lo = limits.upper[j] - slack, limits.lower[j] + slack
            else:
                hi = limits.symmetric(k)[j] - slack
                lo = -hi
            g[row : row + m, cols] = b
            h[row : row + m] = hi
            g[row + m : row + 2 * m, cols] = -b
            h[row + m : row + 2 * m] = -lo
            row += 2 * m
    return g, h
