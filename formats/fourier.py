"""Finite Fourier series excitation (Swevers form, contracts §6).

Joint j follows, with ω_f = 2π·f_base,

    q_j(t) = q0_j + Σ_l [ a_jl/(ω_f·l)·sin(ω_f·l·t) − b_jl/(ω_f·l)·cos(ω_f·l·t) ],  l = 1..H

so ``qd_j = Σ a_jl·cos(ω_f·l·t) + b_jl·sin(ω_f·l·t)``: the coefficients are velocity amplitudes
(rad/s). Every derivative is linear in the coefficients, which makes all limit constraints on a
time grid linear (:func:`basis`) and gives simple analytic bounds (:func:`derivative_bounds`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivegain.errors import TrajectoryError

#: Highest derivative order :func:`basis` and :func:`derivative_bounds` provide (0 = position).
MAX_ORDER = 5


@dataclass(frozen=True)
class FourierTrajectory:
    """A periodic excitation, one finite Fourier series per joint.

    Attributes
    ----------
    base_frequency_hz
        Base frequency f_base, Hz (the period is 1/f_base).
    q0
        Offsets, rad, shape (n,).
    a, b
        Sine and cosine coefficients, rad/s, shape (n, H).
    periods
        Number of periods the excitation runs.
    """

    base_frequency_hz: float
    q0: np.ndarray
    a: np.ndarray
    b: np.ndarray
    periods: int = 1

    def __post_init__(self) -> None:
        q0 = np.asarray(self.q0, dtype=float)
        a = np.atleast_2d(np.asarray(self.a, dtype=float))
        b = np.atleast_2d(np.asarray(self.b, dtype=float))
        if q0.ndim != 1 or a.shape != b.shape or a.shape[0] != q0.shape[0]:
            raise TrajectoryError(
                f"inconsistent shapes: q0 {q0.shape}, a {a.shape}, b {b.shape} "
                "(expected (n,), (n, H), (n, H))"
            )
        if not self.base_frequency_hz > 0.0:
            raise TrajectoryError(f"base frequency must be > 0, got {self.base_frequency_hz}")
        if self.periods < 1:
            raise TrajectoryError(f"periods must be >= 1, got {self.periods}")
        object.__setattr__(self, "q0", q0)
        object.__setattr__(self, "a", a)
        object.__setattr__(self, "b", b)

    @property
    def n(self) -> int:
        """Number of joints."""
        return int(self.q0.shape[0])

    @property
    def harmonics(self) -> int:
        """Number of harmonics H."""
        return int(self.a.shape[1])

    @property
    def omega(self) -> float:
        """Base angular frequency ω_f, rad/s."""
        return 2.0 * np.pi * self.base_frequency_hz

    @property
    def period_s(self) -> float:
        """One period, s."""
        return 1.0 / self.base_frequency_hz

    @property
    def duration_s(self) -> float:
        """The whole excitation (all periods), s."""
        return self.periods * self.period_s

    def coefficients(self) -> np.ndarray:
        """Coefficient matrix (n, 1 + 2H): per joint ``[q0, a_1..a_H, b_1..b_H]``."""
        return np.hstack([self.q0[:, None], self.a, self.b])

    @classmethod
    def from_coefficients(
        cls, base_frequency_hz: float, theta: np.ndarray, periods: int = 1
    ) -> FourierTrajectory:
        """Inverse of :meth:`coefficients` (``theta`` may be flat, joint after joint)."""
        th = np.asarray(theta, dtype=float)
        if th.ndim == 1:
            raise TrajectoryError("theta must have shape (n, 1 + 2H)")
        h = (th.shape[1] - 1) // 2
        return cls(
            base_frequency_hz,
            th[:, 0].copy(),
            th[:, 1 : 1 + h].copy(),
            th[:, 1 + h :].copy(),
            periods,
        )

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration and jerk at times ``t`` (s, from the series' origin).

        The series is evaluated as written for any t (it is periodic); limiting it to
        ``[0, duration_s]`` is the job of :class:`~drivegain.excite.motion.Motion`.

        Returns
        -------
        tuple of numpy.ndarray
            ``q`` (rad), ``qd`` (rad/s), ``qdd`` (rad/s²), ``qddd`` (rad/s³), each (N, n).
        """
        theta = self.coefficients()
        out = []
        for order in range(4):
            out.append(basis(np.atleast_1d(t), self.omega, self.harmonics, order) @ theta.T)
        return out[0], out[1], out[2], out[3]

    def state_at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration (n,) at one time ``t`` (s)."""
        q, qd, qdd, _ = self.evaluate(np.array([t]))
        return q[0], qd[0], qdd[0]

    def with_periods(self, periods: int) -> FourierTrajectory:
        """The same series run for ``periods`` periods."""
        return FourierTrajectory(self.base_frequency_hz, self.q0, self.a, self.b, periods)

    def scaled(self, factor: float) -> FourierTrajectory:
        """The series with every amplitude multiplied by ``factor`` (same offsets q0)."""
        return FourierTrajectory(
            self.base_frequency_hz, self.q0, self.a * factor, self.b * factor, self.periods
        )


def basis(t: np.ndarray, omega: float, harmonics: int, order: int) -> np.ndarray:
    """Basis matrix B (N, 1 + 2H) with ``d^order q_j/dt^order (t) = B @ [q0, a, b]_j``.

    Parameters
    ----------
    t
        Times, s, shape (N,).
    omega
        Base angular frequency ω_f, rad/s.
    harmonics
        Number of harmonics H.
    order
        Derivative order, 0 (position, rad) to :data:`MAX_ORDER`.
    """
    if not 0 <= order <= MAX_ORDER:
        raise TrajectoryError(f"order must be 0..{MAX_ORDER}, got {order}")
    t = np.asarray(t, dtype=float).reshape(-1)
    w = omega * np.arange(1, harmonics + 1)
    phase = np.outer(t, w)
    s, c = np.sin(phase), np.cos(phase)
    # q = a/w·sin − b/w·cos; each derivative multiplies by w and shifts the phase by π/2:
    # d^k/dt^k sin = w^k sin(x + kπ/2), so the a-column is w^(k-1)·sin(x + kπ/2) and the
    # b-column −w^(k-1)·cos(x + kπ/2).
    scale = w ** (order - 1)
    shifted = [(s, c), (c, -s), (-s, -c), (-c, s)][order % 4]
    out = np.empty((t.shape[0], 1 + 2 * harmonics))
    out[:, 0] = 1.0 if order == 0 else 0.0
    out[:, 1 : 1 + harmonics] = shifted[0] * scale
    out[:, 1 + harmonics :] = -shifted[1] * scale
    return out


def derivative_bounds(fourier: FourierTrajectory) -> np.ndarray:
    """Analytic bounds of |d^k q_j/dt^k − δ_k0·q0_j| over all t, for k = 0..MAX_ORDER.

    With c_jl = sqrt(a_jl² + b_jl²), harmonic l of derivative k has amplitude c_jl·(ω_f·l)^(k−1),
    so the sum over l bounds it (reached only if all harmonics peak together).

    Returns
    -------
    numpy.ndarray
        Shape (MAX_ORDER + 1, n), in rad, rad/s, rad/s², rad/s³, rad/s⁴, rad/s⁵.
    """
    c = np.hypot(fourier.a, fourier.b)
    w = fourier.omega * np.arange(1, fourier.harmonics + 1)
    return np.stack([(c * w ** (k - 1)).sum(axis=1) for k in range(MAX_ORDER + 1)])


def start_state(fourier: FourierTrajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """State (q, qd, qdd) at t = 0, which is also the state at the end of every period."""
    return fourier.state_at(0.0)
