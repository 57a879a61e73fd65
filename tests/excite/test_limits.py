"""Limit checks, working limits and the linear grid constraints."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from drivegain.config import load_robot, resource_path
from drivegain.errors import ConfigError, TrajectoryError
from drivegain.excite.limits import ExcitationLimits, check_limits, grid_constraints
from drivegain.formats.fourier import FourierTrajectory


@pytest.fixture(scope="module")
def robot():
    return load_robot(resource_path("tx40.toml"))


def test_inside_passes_and_each_violation_is_named(robot) -> None:
    n = robot.n
    q = np.zeros((5, n))
    zeros = np.zeros((5, n))
    check_limits(robot, q, zeros, zeros, zeros)
    cases = [
        (0, 1, robot.upper[1] + 0.01, "j2: position"),
        (1, 2, -robot.velocity_limits[2] * 1.01, "j3: velocity"),
        (2, 4, robot.acceleration_limits[4] * 1.01, "j5: acceleration"),
        (3, 5, robot.jerk_limits[5] * 1.01, "j6: jerk"),
    ]
    for k, j, value, text in cases:
        arrays = [q.copy(), zeros.copy(), zeros.copy(), zeros.copy()]
        arrays[k][3, j] = value
        with pytest.raises(TrajectoryError, match=text) as err:
            check_limits(robot, *arrays, times=np.arange(5) * 0.5)
        assert "t = 1.5000 s" in str(err.value)
        assert "\n" not in str(err.value)


def test_margin_fraction_and_nan(robot) -> None:
    q = np.zeros((1, robot.n))
    q[0, 0] = robot.upper[0] - 0.05
    check_limits(robot, q, q * 0, q * 0)
    with pytest.raises(TrajectoryError, match="j1: position"):
        check_limits(robot, q, q * 0, q * 0, margin=0.1)
    qd = np.zeros((1, robot.n))
    qd[0, 3] = 0.9 * robot.velocity_limits[3]
    check_limits(robot, q * 0, qd, q * 0)
    with pytest.raises(TrajectoryError, match="j4: velocity"):
        check_limits(robot, q * 0, qd, q * 0, fraction=0.8)
    qd[0, 3] = np.nan
    with pytest.raises(TrajectoryError, match="j4: velocity is not finite"):
        check_limits(robot, q * 0, qd, q * 0)


def test_working_limits(robot) -> None:
    lim = ExcitationLimits.from_robot(robot, 0.2, 0.5)
    np.testing.assert_allclose(lim.lower, robot.lower + 0.2)
    np.testing.assert_allclose(lim.upper, robot.upper - 0.2)
    np.testing.assert_allclose(lim.jerk, 0.5 * robot.jerk_limits)
    with pytest.raises(ConfigError, match=r"j2: position range .* narrower|not wider") as err:
        ExcitationLimits.from_robot(robot, 2.2)
    assert err.value.key == "joint[1].position_limits"
    assert str(robot.source) in str(err.value)
    with pytest.raises(ConfigError, match="fraction"):
        ExcitationLimits.from_robot(robot, 0.1, 1.5)


def test_grid_constraints_match_sampled_limits(robot) -> None:
    """G θ <= h must hold exactly when the sampled values are inside the tightened limits."""
    lim = ExcitationLimits.from_robot(robot)
    h_count = 3
    f0 = FourierTrajectory(0.1, lim.middle, np.zeros((6, h_count)), np.zeros((6, h_count)))
    t = np.arange(50) * f0.period_s / 50
    g, h = grid_constraints(t, f0.omega, h_count, lim)
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.normal(size=(6, h_count)) * rng.uniform(0.1, 2.0)
        b = rng.normal(size=(6, h_count)) * rng.uniform(0.1, 2.0)
        f = dataclasses.replace(f0, a=a, b=b)
        feasible_grid = bool(np.all(g @ f.coefficients().reshape(-1) <= h))
        q, qd, qdd, qddd = f.evaluate(t)
        dt = t[1] - t[0]
        top = f.omega * h_count
        slack = [
            dt**2 / 8 * lim.acceleration,
            dt**2 / 8 * lim.jerk,
            dt**2 / 8 * lim.jerk * top,
            dt**2 / 8 * lim.jerk * top**2,
        ]
        inside = (
            np.all(q <= lim.upper - slack[0])
            and np.all(q >= lim.lower + slack[0])
            and np.all(np.abs(qd) <= lim.velocity - slack[1])
            and np.all(np.abs(qdd) <= lim.acceleration - slack[2])
            and np.all(np.abs(qddd) <= lim.jerk - slack[3])
        )
        assert feasible_grid == bool(inside)
