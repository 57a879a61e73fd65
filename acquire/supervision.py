"""Checks run on every cycle: following error, position limits and speed of the measured motion.

The drives report their position sampled at the SYNC, before they apply the target that came with
it, so the reference for the following error of cycle k is the setpoint sent at cycle k−1.

Reaction time: cycle k is checked once its TPDOs are in, before SYNC k+1 in lockstep (same cycle)
and after SYNC k+1 in realtime (pipelined), so a limit exceeded at cycle k stops the loop before
SYNC k+1, resp. k+2 (docs/realtime.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivegain.config.robot import Robot
from drivegain.errors import DriveError


@dataclass(frozen=True)
class Supervision:
    """Limits checked on every cycle.

    ``following_error`` (rad, per joint): largest allowed |setpoint − position|;
    ``position_margin`` (rad): how far past the robot's position limits a measured position may be;
    ``velocity_margin``: a measured speed above this factor times the velocity limit is a fault;
    ``max_overruns``: consecutive realtime deadline misses (more than one period late) tolerated.
    """

    following_error: np.ndarray
    position_margin: float = 0.02
    velocity_margin: float = 1.25
    max_overruns: int = 3


class SupervisionFault(DriveError):
    """A supervised limit was exceeded on a drive (node id in the error)."""


class Supervisor:
    """Per-cycle supervision of one run.

    Parameters
    ----------
    robot
        Limits and node ids.
    limits
        The ``[acquisition]`` supervision settings.
    period_s
        SYNC period, s (for the measured speed).
    """

    def __init__(self, robot: Robot, limits: Supervision, period_s: float):
        self.robot = robot
        self.node_ids = robot.node_ids
        self.names = robot.joint_names
        self.following_error = np.asarray(limits.following_error, dtype=float)
        self.lower = robot.lower - limits.position_margin
        self.upper = robot.upper + limits.position_margin
        self.speed_limit = robot.velocity_limits * limits.velocity_margin
        self.period_s = period_s
        self._last_position: np.ndarray | None = None
        self._last_setpoint: np.ndarray | None = None
        self.max_following_error = np.zeros(robot.n)

    def reset(self) -> None:
        """Forget the previous cycle (after an enable, a stop...)."""
        self._last_position = None
        self._last_setpoint = None

    def check(
        self,
        cycle: int,
        position: np.ndarray,
        setpoint: np.ndarray,
        interval_s: float | None = None,
    ) -> None:
        """Check one cycle's measured positions against the limits.

        Parameters
        ----------
        cycle
            Cycle index (for the message).
        position
            Measured joint positions at this SYNC, rad.
        setpoint
            The setpoint sent with this SYNC, rad (becomes the reference of the next check).
        interval_s
            Time since the previous SYNC, s (realtime: the measured interval, so that a late
            SYNC is not mistaken for a fast joint); default the period.

        Raises
        ------
        SupervisionFault
            Naming the joint, its node id, the value and the limit.
        """
        pos = np.asarray(position, dtype=float)
        if not np.all(np.isfinite(pos)):
            j = int(np.flatnonzero(~np.isfinite(pos))[0])
            self._fault(j, f"non-finite position at cycle {cycle}")
        below, above = pos < self.lower, pos > self.upper
        if np.any(below | above):
            j = int(np.flatnonzero(below | above)[0])
            lim = self.lower[j] if below[j] else self.upper[j]
            self._fault(
                j, f"position {pos[j]:+.4f} rad beyond limit {lim:+.4f} rad at cycle {cycle}"
            )
        if self._last_setpoint is not None:
            err = np.abs(self._last_setpoint - pos)
            np.maximum(self.max_following_error, err, out=self.max_following_error)
            self._check_below(err, self.following_error, "following error", "rad", 4, cycle)
        if self._last_position is not None:
            dt = self.period_s if interval_s is None else max(interval_s, self.period_s)
            speed = np.abs(pos - self._last_position) / dt
            self._check_below(speed, self.speed_limit, "speed", "rad/s", 3, cycle)
        self._last_position = pos
        self._last_setpoint = np.array(setpoint, dtype=float)

    def _check_below(
        self,
        value: np.ndarray,
        limit: np.ndarray,
        what: str,
        unit: str,
        decimals: int,
        cycle: int,
    ) -> None:
        """Fault on the first joint whose ``value`` exceeds its ``limit`` (both in ``unit``)."""
        over = value > limit
        if np.any(over):
            j = int(np.flatnonzero(over)[0])
            self._fault(
                j,
                f"{what} {value[j]:.{decimals}f} {unit} above {limit[j]:.{decimals}f} {unit} "
                f"at cycle {cycle}",
            )

    def _fault(self, j: int, text: str) -> None:
        raise SupervisionFault(f"{self.names[j]}: {text}", node=self.node_ids[j])
