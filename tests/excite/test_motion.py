"""Approach + excitation + retreat with ruckig, and stops: limits at 1 kHz, continuity."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from drivegain.config import load_robot, resource_path
from drivegain.errors import TrajectoryError
from drivegain.excite.limits import ExcitationLimits
from drivegain.excite.trajectory import Phase, load_trajectory, plan_motion, plan_stop
from drivegain.formats.fourier import FourierTrajectory


@pytest.fixture(scope="module")
def robot():
    return load_robot(resource_path("tx40.toml"))


@pytest.fixture(scope="module")
def shipped():
    return load_trajectory(resource_path("tx40-excitation.json"))


def assert_inside_limits_at_1khz(robot, motion) -> None:
    """Plain numpy against the robot file's limits; jerk from differences of acceleration
    (a difference quotient never exceeds the largest jerk in between)."""
    dt = 1e-3
    t = np.arange(0.0, motion.duration_s + dt, dt)
    q, qd, qdd = motion.sample(t)
    tol = 1e-9
    assert np.all(q >= robot.lower - tol) and np.all(q <= robot.upper + tol)
    assert np.all(np.abs(qd) <= robot.velocity_limits * (1 + tol))
    assert np.all(np.abs(qdd) <= robot.acceleration_limits * (1 + tol))
    jerk = np.diff(qdd, axis=0) / dt
    assert np.all(np.abs(jerk) <= robot.jerk_limits * (1 + 1e-6))
    # and the working limits (margins) the planner promises
    lim = ExcitationLimits.from_robot(robot)
    start = q[0]
    assert np.all(q >= np.minimum(lim.lower, start) - tol)
    assert np.all(q <= np.maximum(lim.upper, start) + tol)
    assert np.all(np.abs(qd) <= lim.velocity * (1 + tol))
    assert np.all(np.abs(qdd) <= lim.acceleration * (1 + tol))
    assert np.all(np.abs(jerk) <= lim.jerk * (1 + 1e-6))


def test_whole_motion_inside_every_limit_at_1khz(robot, shipped) -> None:
    rng = np.random.default_rng(0)
    lim = ExcitationLimits.from_robot(robot)
    starts = [np.zeros(robot.n)] + [rng.uniform(lim.lower, lim.upper) for _ in range(3)]
    for q_start in starts:
        motion = plan_motion(robot, shipped.fourier, q_start)
        assert_inside_limits_at_1khz(robot, motion)
        q_end, qd_end, qdd_end = (x[0] for x in motion.sample(motion.duration_s))
        np.testing.assert_allclose(q_end, q_start, atol=1e-9)
        np.testing.assert_allclose(qd_end, 0.0, atol=1e-9)
        np.testing.assert_allclose(qdd_end, 0.0, atol=1e-9)


def test_continuity_at_the_joins(robot, shipped) -> None:
    motion = plan_motion(robot, shipped.fourier, np.zeros(robot.n))
    bounds = motion.phase_bounds
    assert list(bounds) == [Phase.APPROACH, Phase.EXCITATION, Phase.RETREAT]
    assert bounds[Phase.EXCITATION][1] - bounds[Phase.EXCITATION][0] == pytest.approx(
        shipped.fourier.duration_s
    )
    series = shipped.fourier
    for join, series_time in (
        (bounds[Phase.EXCITATION][0], 0.0),
        (bounds[Phase.RETREAT][0], series.duration_s),
    ):
        # The series' own state at the join, against the motion just before and just after.
        expected = series.state_at(series_time)
        eps = 1e-7
        before = motion.sample(join - eps)
        after = motion.sample(join + eps)
        # Over eps the state moves by at most eps times the next derivative's limit.
        rates = (robot.velocity_limits, robot.acceleration_limits, robot.jerk_limits)
        for x_b, x_a, x_e, rate in zip(before, after, expected, rates, strict=True):
            assert np.all(np.abs(x_b[0] - x_e) <= eps * rate + 1e-9)
            assert np.all(np.abs(x_a[0] - x_e) <= eps * rate + 1e-9)
    assert motion.phase(-1.0) is Phase.APPROACH
    assert motion.phase(bounds[Phase.EXCITATION][0] + 1.0) is Phase.EXCITATION
    assert motion.phase(bounds[Phase.RETREAT][0] + 0.01) is Phase.RETREAT
    assert motion.phase(motion.duration_s) is Phase.DONE


def test_sampling_is_rate_independent(robot, shipped) -> None:
    motion = plan_motion(robot, shipped.fourier, np.zeros(robot.n))
    t = np.linspace(0.0, motion.duration_s, 977)
    one_by_one = np.array([motion.sample(ti)[0][0] for ti in t[::50]])
    np.testing.assert_allclose(motion.sample(t)[0][::50], one_by_one)


def test_approach_that_must_overshoot_a_limit_is_refused(robot) -> None:
    """ruckig ignores position limits: a start state moving down must be approached from above
    it. With a working range ending just above that state the planner has to refuse."""
    w = 2 * np.pi * 0.1
    amp, phi = 1.0, 0.3  # j1: q = amp·cos(w t + phi), just after its peak, moving down
    a = np.zeros((robot.n, 1))
    b = np.zeros((robot.n, 1))
    # amp·cos(wt + phi) = a/w·sin(wt) − b/w·cos(wt) with a = −amp·w·sin(phi), b = −amp·w·cos(phi)
    a[0, 0] = -amp * w * np.sin(phi)
    b[0, 0] = -amp * w * np.cos(phi)
    f = FourierTrajectory(0.1, np.zeros(robot.n), a, b)
    q0 = f.state_at(0.0)[0][0]
    assert q0 == pytest.approx(amp * np.cos(phi))
    q_start = np.zeros(robot.n)
    q_start[0] = -2.0
    motion = plan_motion(robot, f, q_start)  # fine with the default working range
    q = motion.sample(np.linspace(0.0, motion.phase_bounds[Phase.APPROACH][1], 2001))[0]
    overshoot = q[:, 0].max() - q0
    assert overshoot > 1e-4  # ruckig does pass above the start state
    lim = ExcitationLimits.from_robot(robot)
    tight = dataclasses.replace(lim, upper=np.where(np.arange(robot.n) == 0, q0 + 1e-4, lim.upper))
    with pytest.raises(TrajectoryError, match=r"approach: j1 would reach .* upper working limit"):
        plan_motion(robot, f, q_start, limits=tight)


def test_excitation_or_pose_outside_the_limits_is_refused(robot, shipped) -> None:
    with pytest.raises(TrajectoryError, match="start pose: j2"):
        bad = np.zeros(robot.n)
        bad[1] = robot.upper[1] + 0.1
        plan_motion(robot, shipped.fourier, bad)
    fast = shipped.fourier.scaled(3.0)
    with pytest.raises(TrajectoryError, match="excitation: j"):
        plan_motion(robot, fast, np.zeros(robot.n))
    with pytest.raises(TrajectoryError, match="not finite"):
        plan_motion(robot, shipped.fourier, np.full(robot.n, np.nan))


def test_stop_from_states_along_the_motion(robot, shipped) -> None:
    motion = plan_motion(robot, shipped.fourier, np.zeros(robot.n))
    for t in np.linspace(0.3, motion.duration_s - 0.3, 7):
        q, qd, qdd = (x[0] for x in motion.sample(t))
        stop = plan_stop(robot, q, qd, qdd)
        assert list(stop.phase_bounds) == [Phase.STOP]
        s0 = stop.initial_state
        for x, y in zip(s0, (q, qd, qdd), strict=True):
            np.testing.assert_allclose(x, y, atol=1e-9)
        assert_stop_ok(robot, stop)


def assert_stop_ok(robot, stop) -> None:
    dt = 1e-3
    t = np.arange(0.0, stop.duration_s + dt, dt)
    _, qd, qdd = stop.sample(t)
    jerk = np.diff(qdd, axis=0) / dt
    assert np.all(np.abs(jerk) <= robot.jerk_limits * (1 + 1e-6))
    assert np.all(np.abs(qd) <= robot.velocity_limits * (1 + 1e-9))
    assert np.all(np.abs(qdd) <= robot.acceleration_limits * (1 + 1e-9))
    _, qd_end, qdd_end = (x[0] for x in stop.sample(stop.duration_s))
    np.testing.assert_allclose(qd_end, 0.0, atol=1e-9)
    np.testing.assert_allclose(qdd_end, 0.0, atol=1e-9)
    # a stop is short: at most the time to brake from the velocity limit twice over
    assert stop.duration_s < 2 * np.max(
        robot.velocity_limits / robot.acceleration_limits
        + robot.acceleration_limits / robot.jerk_limits
    )


def test_stop_from_beyond_the_limits_still_comes_to_rest(robot) -> None:
    q = np.zeros(robot.n)
    qd = 1.2 * robot.velocity_limits * np.array([1, -1, 1, -1, 1, -1])
    qdd = 1.1 * robot.acceleration_limits
    stop = plan_stop(robot, q, qd, qdd)
    _, qd_end, _ = (x[0] for x in stop.sample(stop.duration_s))
    np.testing.assert_allclose(qd_end, 0.0, atol=1e-9)


def test_stop_near_a_limit_warns_instead_of_refusing(robot) -> None:
    q = np.zeros(robot.n)
    q[0] = robot.upper[0] - 0.01
    qd = np.zeros(robot.n)
    qd[0] = robot.velocity_limits[0]
    stop = plan_stop(robot, q, qd)
    assert stop.warnings and "j1" in stop.warnings[0]
    assert stop.final_position[0] > robot.upper[0]
