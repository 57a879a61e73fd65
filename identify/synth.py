"""Inverse-dynamics simulation of runs without a bus: the known answer for the estimators.

A :class:`SyntheticRun` is what a recording would hold if the robot followed ``(q, qd, qdd)``
exactly: current references that produce the true joint torques through the true drive gains
(plus torque noise), and encoder positions quantised like a real encoder. Velocities and
accelerations are returned exact (analytic), so noise-free tests can skip the filters; noisy tests
must differentiate the quantised ``q`` instead, as the real pipeline does.

Also here: a random Fourier excitation (the series of contracts §6) scaled into the joint limits,
good enough to excite every base parameter in tests and benchmarks. The optimised
excitation of the product lives in :mod:`drivegain.excite`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from drivegain.config.excitation import DEFAULT_BASE_FREQUENCY_HZ, DEFAULT_HARMONICS
from drivegain.config.payload import Payload
from drivegain.config.robot import Robot, WristFriction
from drivegain.config.truth import Truth
from drivegain.dynamics.base import BaseParameters, base_parameters
from drivegain.dynamics.model import RobotModel, build_model
from drivegain.dynamics.params import truth_vector, with_payload
from drivegain.dynamics.regressor import standard_regressor
from drivegain.dynamics.transmission import currents_for_torque, joint_torque
from drivegain.errors import InputError
from drivegain.formats.fourier import FourierTrajectory

#: Samples per regressor evaluation: bounds the (chunk, n, 86) temporary to a few tens of MB.
CHUNK = 8192


@dataclass(frozen=True)
class SyntheticRun:
    """One simulated run (all arrays (N, n), joint side, controller convention).

    Attributes
    ----------
    q
        Measured (quantised) joint positions, rad.
    q_true, qd, qdd
        Exact positions (rad), velocities (rad/s) and accelerations (rad/s²).
    tau_true
        True joint torques, N·m (rigid body, rotor inertia, friction, coupled wrist, payload).
    tau
        Joint torques the recorded currents stand for with the true gains: ``tau_true`` + noise.
    current_reference
        Current references, A: ``joint_torque(robot, current_reference, gains) == tau``.
    gains
        True drive gains used, N·m/A.
    """

    q: np.ndarray
    q_true: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau_true: np.ndarray
    tau: np.ndarray
    current_reference: np.ndarray
    gains: np.ndarray


def _per_joint(value: float | np.ndarray, n: int, name: str) -> np.ndarray:
    a = np.broadcast_to(np.asarray(value, dtype=float), (n,)).copy()
    if np.any(a < 0.0) or not np.all(np.isfinite(a)):
        raise InputError(f"must be finite and >= 0, got {value!r}", key=name)
    return a


def quantise(q: np.ndarray, quantum: float | np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Encoder reading of ``q``: round to a grid of step ``quantum`` (rad) with a random origin.

    The grid origin is drawn per joint (an encoder's zero is not aligned with the joint's), so
    different seeds give different quantisation errors along the same trajectory.
    """
    q = np.asarray(q, dtype=float)
    step = _per_joint(quantum, q.shape[1], "quantum")
    out = q.copy()
    for j in np.flatnonzero(step > 0.0):
        origin = rng.uniform(0.0, step[j])
        out[:, j] = np.round((q[:, j] - origin) / step[j]) * step[j] + origin
    return out


def true_torque(
    model: RobotModel,
    chi: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    friction: WristFriction | str | None = None,
) -> np.ndarray:
    """Joint torques (N·m) of standard parameters ``chi`` along a trajectory, in chunks."""
    q, qd, qdd = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (q, qd, qdd))
    out = np.empty(q.shape)
    for s in range(0, q.shape[0], CHUNK):
        sl = slice(s, s + CHUNK)
        out[sl] = standard_regressor(model, q[sl], qd[sl], qdd[sl], friction) @ chi
    return out


def simulate_run(
    model: RobotModel,
    truth: Truth,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    *,
    payload: Payload | None = None,
    gains: np.ndarray | None = None,
    torque_noise: float | np.ndarray = 0.0,
    quantum: float | np.ndarray = 0.0,
    rng: np.random.Generator | None = None,
    friction: WristFriction | str | None = None,
    current_noise: float | np.ndarray = 0.0,
) -> SyntheticRun:
    """Simulate one recording along an exactly tracked trajectory.

    Parameters
    ----------
    model
        The robot model.
    truth
        True dynamic parameters (and true gains, used unless ``gains`` is given).
    q, qd, qdd
        Trajectory, (N, n): rad, rad/s, rad/s².
    payload
        Payload fixed to the robot for this run (its NaN values count as zero).
    gains
        True drive gains, N·m/A (default: ``truth.gains``).
    torque_noise
        Standard deviation of white Gaussian joint-torque noise, N·m (scalar or per joint).
        The noise enters through the currents, as current-reference noise does.
    quantum
        Encoder quantum at the joint, rad (scalar or per joint); 0 = exact positions.
    rng
        Random generator (default: seed 0).
    friction
        Coupled-wrist friction form of the truth (default: the robot file's).
    current_noise
        Standard deviation of white noise on each drive's current reference, A (scalar or per
        drive): through the coupled wrist, drive 6's noise reaches joints 5 and 6.

    Raises
    ------
    InputError
        Trajectory arrays of different shapes or not n columns; a negative or non-finite noise
        level or quantum.
    """
    robot = model.robot
    n = robot.n
    rng = np.random.default_rng(0) if rng is None else rng
    q, qd, qdd = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (q, qd, qdd))
    if not q.shape == qd.shape == qdd.shape or q.shape[1] != n:
        raise InputError(
            f"must all have shape (N, {n}), got {q.shape}, {qd.shape}, {qdd.shape}",
            key="q, qd, qdd",
        )
    chi = truth_vector(robot, truth)
    if payload is not None:
        chi = with_payload(robot, chi, payload)
    g = np.asarray(truth.gains if gains is None else gains, dtype=float)
    tau_true = true_torque(model, chi, q, qd, qdd, friction)
    sigma = _per_joint(torque_noise, n, "torque_noise")
    current = currents_for_torque(
        robot, tau_true + rng.standard_normal(tau_true.shape) * sigma, g
    ) + rng.standard_normal(tau_true.shape) * _per_joint(current_noise, n, "current_noise")
    tau = joint_torque(robot, current, g)
    return SyntheticRun(
        q=quantise(q, quantum, rng),
        q_true=q,
        qd=qd,
        qdd=qdd,
        tau_true=tau_true,
        tau=tau,
        current_reference=current,
        gains=g,
    )


def model_with_friction(model: RobotModel, friction: WristFriction | str) -> RobotModel:
    """The same model with another coupled-wrist friction form as the robot's default."""
    form = WristFriction(friction)
    if model.robot.wrist_friction is form:
        return model
    robot: Robot = replace(model.robot, wrist_friction=form)
    return build_model(robot)


def scaled_sum_of_sines(
    robot: Robot,
    rng: np.random.Generator,
    *,
    base_frequency_hz: float = DEFAULT_BASE_FREQUENCY_HZ,
    harmonics: int = DEFAULT_HARMONICS,
    margin: float = 0.8,
) -> FourierTrajectory:
    """A random sum of sines that uses up to ``margin`` of every joint limit.

    Coefficients are Gaussian with amplitudes falling as 1/l; each joint is then scaled so
    that its position excursion, speed and acceleration stay within ``margin`` of the robot's
    limits (checked on a grid fine enough for the highest harmonic).
    """
    n = robot.n
    harm = np.arange(1, harmonics + 1)
    a = rng.standard_normal((n, harmonics)) / harm
    b = rng.standard_normal((n, harmonics)) / harm
    lo, hi = robot.lower, robot.upper
    mid = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    # Centre away from the middle so gravity torques are not symmetric about zero.
    q0 = mid + rng.uniform(-0.2, 0.2, n) * half
    room = np.minimum(hi - q0, q0 - lo)
    period = 1.0 / base_frequency_hz
    t = np.linspace(0.0, period, 64 * harmonics * 4, endpoint=False)
    unit = FourierTrajectory(base_frequency_hz, np.zeros(n), a, b)
    q, qd, qdd, _ = unit.evaluate(t)
    k = np.min(
        np.stack(
            [
                margin * room / np.abs(q).max(axis=0),
                margin * robot.velocity_limits / np.abs(qd).max(axis=0),
                margin * robot.acceleration_limits / np.abs(qdd).max(axis=0),
            ]
        ),
        axis=0,
    )
    # Peaks between grid points exceed the sampled ones by < 1e-4 (256 points per period of
    # the highest harmonic): keep a margin on that.
    k /= 1.001
    return FourierTrajectory(base_frequency_hz, q0, a * k[:, None], b * k[:, None])


def exciting_sum_of_sines(
    model: RobotModel,
    rng: np.random.Generator,
    *,
    base_frequency_hz: float = DEFAULT_BASE_FREQUENCY_HZ,
    harmonics: int = DEFAULT_HARMONICS,
    candidates: int = 20,
    margin: float = 0.8,
    base: BaseParameters | None = None,
) -> FourierTrajectory:
    """The best of ``candidates`` random sums of sines by condition number of the base regressor.

    A cheap stand-in for the excitation optimiser, for tests and benchmarks: the condition
    number is that of the column-normalised standard regressor restricted to its independent
    columns, sampled over one period. ``base``: the model's base parameters (computed when not
    given).

    Raises
    ------
    InputError
        ``candidates`` < 1.
    """
    if candidates < 1:
        raise InputError(f"must be at least 1, got {candidates}", key="candidates")
    bp = base_parameters(model) if base is None else base
    period = 1.0 / base_frequency_hz
    t = np.linspace(0.0, period, 200, endpoint=False)
    best, best_cond = None, np.inf
    for _ in range(candidates):
        cand = scaled_sum_of_sines(
            model.robot,
            rng,
            base_frequency_hz=base_frequency_hz,
            harmonics=harmonics,
            margin=margin,
        )
        w = standard_regressor(model, *cand.evaluate(t)[:3])
        wb = bp.columns(w.transpose(1, 0, 2).reshape(-1, w.shape[2]))
        wb = wb / np.linalg.norm(wb, axis=0)
        cond = float(np.linalg.cond(wb))
        if cond < best_cond:
            best, best_cond = cand, cond
    # Invariant: at least one candidate and finite condition numbers (a NaN would mean a
    # broken regressor, a programming error).
    assert best is not None
    return best
