"""The whole motion of a run: ruckig approach, Fourier excitation, ruckig retreat; and stops.

ruckig (community edition) is used offline and segment by segment: one trajectory from the
pose at rest to the excitation's start state (q, qd, qdd at t = 0 of the series), one from its
end state back to rest. Intermediate waypoints are never used (the community edition sends them
to a cloud service), and ruckig ignores position limits, so the position extrema of every
segment are checked here.

A :class:`Motion` is sampled at any rate (vectorised over times), continuous in position,
velocity and acceleration at the joins (ruckig reaches the target state exactly).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from enum import Enum
from typing import Protocol

import numpy as np
from ruckig import ControlInterface, InputParameter, Ruckig, RuckigError, Trajectory

from drivegain.config.robot import Robot
from drivegain.errors import TrajectoryError, UsageError
from drivegain.excite.limits import (
    QUANTITIES,
    UNITS,
    ExcitationLimits,
    check_limits,
    fourier_usage,
)
from drivegain.formats.fourier import FourierTrajectory

log = logging.getLogger(__name__)

#: Sampling step of the checks of ruckig segments, s (their limits hold by construction; this
#: is the independent check).
CHECK_DT = 1e-3


class Phase(Enum):
    """Phase of a motion at a given time."""

    APPROACH = "approach"
    EXCITATION = "excitation"
    RETREAT = "retreat"
    STOP = "stop"
    DONE = "done"


class Segment(Protocol):
    """A piece of motion, sampled on its own clock from 0 to ``duration``."""

    duration: float

    def sample(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


@dataclass
class RuckigSegment:
    """A jerk-limited ruckig trajectory (all joints time-synchronised)."""

    trajectory: Trajectory
    duration: float
    n: int

    def sample(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        out = np.empty((3, tau.shape[0], self.n))
        # ruckig extrapolates past its end: clip to the segment.
        for i, ti in enumerate(np.clip(tau, 0.0, self.duration)):
            p, v, a = self.trajectory.at_time(float(ti))
            out[0, i], out[1, i], out[2, i] = p, v, a
        return out[0], out[1], out[2]

    def position_extrema(self) -> tuple[np.ndarray, np.ndarray]:
        """Exact minimum and maximum position of each joint over the segment, rad."""
        ext = self.trajectory.position_extrema
        return np.array([b.min for b in ext]), np.array([b.max for b in ext])

    def max_jerk(self) -> np.ndarray:
        """Largest |jerk| of each joint over the segment (from the profiles), rad/s³."""
        out = np.zeros(self.n)
        for section in self.trajectory.profiles:
            for j, prof in enumerate(section):
                parts = [
                    (prof.j, prof.t),
                    (prof.brake.j, prof.brake.t),
                    (prof.accel.j, prof.accel.t),
                ]
                for jerks, durations in parts:
                    for jk, dt in zip(jerks, durations, strict=False):
                        if dt > 0.0:
                            out[j] = max(out[j], abs(jk))
        return out


@dataclass
class FourierSegment:
    """The excitation: the series from its origin for ``periods`` periods."""

    fourier: FourierTrajectory
    duration: float

    def sample(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q, qd, qdd, _ = self.fourier.evaluate(np.clip(tau, 0.0, self.duration))
        return q, qd, qdd


@dataclass
class Motion:
    """Segments one after the other, sampled at any time.

    Before 0 the motion holds its initial state, after ``duration_s`` its final state (at
    rest: every motion planned here ends at rest).

    Attributes
    ----------
    segments
        ``(phase, start time s, segment)`` in time order.
    duration_s
        Total duration, s.
    phase_bounds
        Start and end time (s) of each phase present.
    fourier
        The excitation, if the motion has one.
    warnings
        Anything the planner accepted but the operator should know (e.g. a stop that must
        cross a position limit).
    """

    segments: list[tuple[Phase, float, Segment]]
    duration_s: float = field(init=False, default=0.0)
    phase_bounds: dict[Phase, tuple[float, float]] = field(init=False, default_factory=dict)
    fourier: FourierTrajectory | None = None
    warnings: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        t = 0.0
        bounds = {}
        for phase, t0, seg in self.segments:
            if abs(t0 - t) > 1e-9:
                raise UsageError(f"segment {phase.value} starts at {t0} s, expected {t} s")
            bounds[phase] = (t0, t0 + seg.duration)
            t = t0 + seg.duration
        self.duration_s = t
        self.phase_bounds = bounds

    def sample(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (rad), velocity (rad/s) and acceleration (rad/s²) at times ``t`` (s).

        Returns
        -------
        tuple of numpy.ndarray
            Each of shape (N, n) (N = number of times).
        """
        times = np.atleast_1d(np.asarray(t, dtype=float))
        if not np.all(np.isfinite(times)):
            raise TrajectoryError("sample times must be finite")
        n = self.n
        q, qd, qdd = (np.empty((times.shape[0], n)) for _ in range(3))
        last = len(self.segments) - 1
        for k, (_phase, t0, seg) in enumerate(self.segments):
            t1 = t0 + seg.duration
            # The first segment also takes earlier times, the last one later times.
            mask = ((times >= t0) | (k == 0)) & ((times < t1) | (k == last))
            if np.any(mask):
                a, b, c = seg.sample(times[mask] - t0)
                q[mask], qd[mask], qdd[mask] = a, b, c
        done = times >= self.duration_s
        if np.any(done):
            # At rest after the end, exactly (no round-off velocity from the last segment).
            qd[done] = 0.0
            qdd[done] = 0.0
        return q, qd, qdd

    @property
    def n(self) -> int:
        seg = self.segments[0][2]
        if isinstance(seg, FourierSegment):
            return seg.fourier.n
        assert isinstance(seg, RuckigSegment)
        return seg.n

    def phase(self, t: float) -> Phase:
        """The phase at time ``t`` (s); ``DONE`` from ``duration_s`` on."""
        if t >= self.duration_s:
            return Phase.DONE
        for phase, t0, seg in self.segments:
            if t < t0 + seg.duration:
                return phase
        return Phase.DONE  # pragma: no cover - guarded above

    @property
    def final_position(self) -> np.ndarray:
        """Where the motion ends (at rest), rad."""
        return self.sample(self.duration_s)[0][0]

    @property
    def initial_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q, qd, qdd = self.sample(0.0)
        return q[0], qd[0], qdd[0]


def _as_state(robot: Robot, x: np.ndarray | None, name: str) -> np.ndarray:
    if x is None:
        return np.zeros(robot.n)
    a = np.asarray(x, dtype=float).reshape(-1)
    if a.shape[0] != robot.n:
        raise TrajectoryError(f"{name} has {a.shape[0]} values, the robot {robot.n} joints")
    if not np.all(np.isfinite(a)):
        raise TrajectoryError(f"{name} is not finite: {a.tolist()}")
    return a


def ruckig_segment(
    q0: np.ndarray,
    qd0: np.ndarray,
    qdd0: np.ndarray,
    target: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    limits: ExcitationLimits,
) -> RuckigSegment:
    """A time-optimal, time-synchronised jerk-limited segment (offline, no waypoints).

    Parameters
    ----------
    q0, qd0, qdd0
        Current state (rad, rad/s, rad/s²).
    target
        Target state; ``None`` for a stop (velocity interface: come to rest as fast as the
        limits allow, wherever that is).
    limits
        Velocity, acceleration and jerk limits (ruckig ignores position limits).

    Raises
    ------
    TrajectoryError
        ruckig refused the input or found no trajectory.
    """
    n = q0.shape[0]
    otg = Ruckig(n)
    inp = InputParameter(n)
    inp.current_position = q0.tolist()
    inp.current_velocity = qd0.tolist()
    inp.current_acceleration = qdd0.tolist()
    if target is None:
        inp.control_interface = ControlInterface.Velocity
        inp.target_velocity = [0.0] * n
        inp.target_acceleration = [0.0] * n
    else:
        inp.target_position = target[0].tolist()
        inp.target_velocity = target[1].tolist()
        inp.target_acceleration = target[2].tolist()
    inp.max_velocity = limits.velocity.tolist()
    inp.max_acceleration = limits.acceleration.tolist()
    inp.max_jerk = limits.jerk.tolist()
    traj = Trajectory(n)
    try:
        otg.calculate(inp, traj)
    except RuckigError as exc:
        raise TrajectoryError(f"ruckig found no trajectory: {exc}") from None
    return RuckigSegment(trajectory=traj, duration=float(traj.duration), n=n)


def _check_segment(
    robot: Robot,
    seg: RuckigSegment,
    limits: ExcitationLimits,
    label: str,
    allowed: tuple[np.ndarray, np.ndarray],
) -> None:
    """Position extrema inside ``allowed``, and velocity/acceleration/jerk inside ``limits``."""
    lo, hi = seg.position_extrema()
    names = robot.joint_names
    for j in range(robot.n):
        tol = 1e-9 * max(1.0, abs(allowed[1][j] - allowed[0][j]))
        if lo[j] < allowed[0][j] - tol or hi[j] > allowed[1][j] + tol:
            bad, side, lim = (
                (lo[j], "lower", allowed[0][j])
                if lo[j] < allowed[0][j] - tol
                else (hi[j], "upper", allowed[1][j])
            )
            raise TrajectoryError(
                f"{label}: {names[j]} would reach {bad:.4g} rad, beyond its {side} working "
                f"limit {lim:.4g} rad (ruckig ignores position limits; start from another pose)"
            )
    jerk = seg.max_jerk()
    over = jerk > limits.jerk * (1.0 + 1e-9)
    if np.any(over):
        j = int(np.argmax(jerk / limits.jerk))
        raise TrajectoryError(
            f"{label}: {names[j]} jerk {jerk[j]:.4g} rad/s³ exceeds {limits.jerk[j]:.4g} rad/s³"
        )
    t = np.arange(0.0, seg.duration + CHECK_DT, CHECK_DT)
    _, qd, qdd = seg.sample(t)
    for k, (x, lim) in enumerate(((qd, limits.velocity), (qdd, limits.acceleration)), start=1):
        ratio = np.abs(x) / (lim * (1.0 + 1e-9))
        if np.any(ratio > 1.0):
            i, jj = (int(v) for v in np.unravel_index(np.argmax(ratio), ratio.shape))
            raise TrajectoryError(
                f"{label}: {names[jj]} {QUANTITIES[k]} {x[i, jj]:.4g} {UNITS[k]} exceeds "
                f"{lim[jj]:.4g} {UNITS[k]} at t = {t[i]:.3f} s"
            )


def check_excitation(
    robot: Robot, fourier: FourierTrajectory, limits: ExcitationLimits | None = None
) -> None:
    """Check a series against limits over continuous time (rigorous bound, see
    :func:`~drivegain.excite.limits.fourier_usage`).

    Parameters
    ----------
    robot
        The robot.
    fourier
        The series.
    limits
        Limits to check against; default: the robot's own limits (no margin, full limits).

    Raises
    ------
    TrajectoryError
        Naming the joint and the limit.
    """
    if fourier.n != robot.n:
        raise TrajectoryError(f"the trajectory has {fourier.n} joints, the robot {robot.n}")
    lim = limits if limits is not None else ExcitationLimits.from_robot(robot, 0.0, 1.0)
    for name, x in (("q0", fourier.q0), ("a", fourier.a), ("b", fourier.b)):
        if not np.all(np.isfinite(x)):
            raise TrajectoryError(f"the series' {name} is not finite")
    if np.any(fourier.q0 < lim.lower) or np.any(fourier.q0 > lim.upper):
        j = int(np.argmax(np.maximum(lim.lower - fourier.q0, fourier.q0 - lim.upper)))
        raise TrajectoryError(
            f"{robot.joint_names[j]}: offset q0 {fourier.q0[j]:.4g} rad is outside "
            f"[{lim.lower[j]:.4g}, {lim.upper[j]:.4g}] rad"
        )
    usage = fourier_usage(fourier, lim)
    if usage.worst > 1.0 + 1e-9:
        k, j = usage.worst_place()
        raise TrajectoryError(
            f"excitation: {robot.joint_names[j]} {QUANTITIES[k]} may reach "
            f"{usage.usage[k, j]:.1%} of its limit"
        )


def plan_motion(
    robot: Robot,
    fourier: FourierTrajectory,
    q_start: np.ndarray,
    periods: int | None = None,
    *,
    q_end: np.ndarray | None = None,
    limits: ExcitationLimits | None = None,
) -> Motion:
    """Plan approach (ruckig) + excitation + retreat (ruckig) from a pose at rest.

    Parameters
    ----------
    robot
        The robot.
    fourier
        The excitation.
    q_start
        Pose at rest the approach starts from, rad (controller convention).
    periods
        Periods of excitation (default: the series' own).
    q_end
        Pose at rest the retreat ends at (default: ``q_start``).
    limits
        Working limits of the ruckig segments (default: the robot's with the default margins).
        The excitation itself is checked against the robot's limits.

    Raises
    ------
    TrajectoryError
        The excitation exceeds a limit, a pose is outside the robot's range, ruckig finds no
        segment, or a segment would leave the working range (names joint and limit).
    """
    lim = limits if limits is not None else ExcitationLimits.from_robot(robot)
    q_start = _as_state(robot, q_start, "start pose")
    q_end = q_start if q_end is None else _as_state(robot, q_end, "end pose")
    f = fourier.with_periods(periods) if periods is not None else fourier
    check_excitation(robot, f)
    for name, pose in (("start pose", q_start), ("end pose", q_end)):
        out = (pose < robot.lower) | (pose > robot.upper)
        if np.any(out):
            j = int(np.argmax(out))
            raise TrajectoryError(
                f"{name}: {robot.joint_names[j]} = {pose[j]:.4g} rad is outside the position "
                f"limits [{robot.lower[j]:.4g}, {robot.upper[j]:.4g}] rad"
            )
    s0 = f.state_at(0.0)
    for k, x in ((1, s0[1]), (2, s0[2])):
        lk = lim.symmetric(k)
        if np.any(np.abs(x) > lk * (1 + 1e-9)):
            j = int(np.argmax(np.abs(x) / lk))
            raise TrajectoryError(
                f"the excitation starts with {robot.joint_names[j]} {QUANTITIES[k]} "
                f"{x[j]:.4g} {UNITS[k]}, above the working limit {lk[j]:.4g} {UNITS[k]}"
            )
    zero = np.zeros(robot.n)
    approach = ruckig_segment(q_start, zero, zero, s0, lim)
    _check_segment(
        robot,
        approach,
        lim,
        "approach",
        (np.minimum(lim.lower, q_start), np.maximum(lim.upper, q_start)),
    )
    s1 = f.state_at(f.duration_s)
    retreat = ruckig_segment(s1[0], s1[1], s1[2], (q_end, zero, zero), lim)
    _check_segment(
        robot,
        retreat,
        lim,
        "retreat",
        (np.minimum(lim.lower, q_end), np.maximum(lim.upper, q_end)),
    )
    ta = approach.duration
    te = ta + f.duration_s
    return Motion(
        segments=[
            (Phase.APPROACH, 0.0, approach),
            (Phase.EXCITATION, ta, FourierSegment(f, f.duration_s)),
            (Phase.RETREAT, te, retreat),
        ],
        fourier=f,
    )


def plan_stop(
    robot: Robot,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray | None = None,
    *,
    limits: ExcitationLimits | None = None,
) -> Motion:
    """Jerk-limited deceleration to rest from the current state (for SIGINT/SIGTERM).

    Time-optimal with the robot's full velocity, acceleration and jerk limits (a state beyond
    them is braked back first, as ruckig does). A stop is always planned: if it must cross a
    position limit the motion says so in ``warnings`` (and the log) instead of refusing.

    Parameters
    ----------
    robot
        The robot.
    q, qd, qdd
        Current state, rad, rad/s, rad/s² (``qdd`` default 0).
    limits
        Limits of the stop (default: the robot's own limits, no margin).

    Raises
    ------
    TrajectoryError
        Non-finite or mis-shaped state.
    """
    lim = limits if limits is not None else ExcitationLimits.from_robot(robot, 0.0, 1.0)
    q = _as_state(robot, q, "q")
    qd = _as_state(robot, qd, "qd")
    qdd = _as_state(robot, qdd, "qdd")
    seg = ruckig_segment(q, qd, qdd, None, lim)
    motion = Motion(segments=[(Phase.STOP, 0.0, seg)])
    lo, hi = seg.position_extrema()
    for j in range(robot.n):
        if lo[j] < robot.lower[j] or hi[j] > robot.upper[j]:
            msg = (
                f"stop: {robot.joint_names[j]} comes to rest beyond its position limits "
                f"([{lo[j]:.4g}, {hi[j]:.4g}] rad against [{robot.lower[j]:.4g}, "
                f"{robot.upper[j]:.4g}] rad)"
            )
            motion.warnings.append(msg)
            log.warning(msg)
    return motion


def check_motion(robot: Robot, motion: Motion, dt: float = CHECK_DT, margin: float = 0.0) -> None:
    """Sample a whole motion every ``dt`` (s) and check it against the robot's limits, jerk
    included (from differences of the sampled acceleration, which never exceed the true jerk).

    Raises
    ------
    TrajectoryError
        Naming the joint, the limit and the time.
    """
    t = np.arange(0.0, motion.duration_s + dt / 2, dt)
    q, qd, qdd = motion.sample(t)
    jerk = np.diff(qdd, axis=0) / dt
    check_limits(robot, q, qd, qdd, margin=margin, times=t)
    check_limits(robot, q[1:], qd[1:], qdd[1:], jerk, margin=margin, times=t[1:])
