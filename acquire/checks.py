"""Checks made before any motion: the bus load of the cycle and the motion against the limits."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drivegain.config.robot import Robot
from drivegain.drivers.bus import BusLoad, bus_load
from drivegain.errors import ConfigError, DataError, TrajectoryError
from drivegain.excite.limits import check_limits
from drivegain.excite.motion import Motion
from drivegain.formats.fourier import FourierTrajectory


def check_bus_load(
    n_nodes: int,
    period_s: float,
    bitrate: int,
    *,
    warn: float,
    config: Path,
    load: BusLoad | None = None,
) -> tuple[BusLoad, str | None]:
    """Refuse a cycle the bus cannot carry; return the load and a warning above ``warn``.

    Parameters
    ----------
    load
        The load computed from the drives' actual PDO mapping (after boot); default: one 8-byte
        RPDO and two 8-byte TPDOs per drive plus SYNC, with worst-case bit stuffing.

    Raises
    ------
    ConfigError
        The cycle needs more than 100 % of the bitrate (names ``acquisition.period_s``).
    """
    if load is None:
        load = bus_load(n_nodes, period_s, bitrate)
    if load.load > 1.0:
        raise ConfigError(
            f"{period_s * 1e3:g} ms with {n_nodes} drives needs {load.load:.0%} of "
            f"{bitrate / 1e6:g} Mbit/s ({load.bits_per_cycle} bits per cycle, at most "
            f"{load.max_rate_hz:.0f} Hz): use a longer period",
            file=config,
            key="acquisition.period_s",
        )
    warning = None
    if load.load > warn:
        warning = (
            f"bus load {load.load:.0%} of {bitrate / 1e6:g} Mbit/s at {1 / period_s:g} Hz is above "
            f"{warn:.0%}: frames may be delayed by other traffic"
        )
    return load, warning


def check_excitation(
    robot: Robot, fourier: FourierTrajectory, period_s: float, *, file: Path
) -> None:
    """Check one period of the excitation against every limit, sampled at least at 1 kHz.

    The series is periodic, so one period covers the whole excitation.

    Raises
    ------
    DataError
        Naming the trajectory file and the joint and limit violated.
    """
    dt = min(period_s, 1e-3)
    t = np.arange(0.0, fourier.period_s + dt / 2, dt)
    q, qd, qdd, qddd = fourier.evaluate(t)
    try:
        check_limits(robot, q, qd, qdd, qddd, label="excitation", times=t)
    except TrajectoryError as exc:
        raise DataError(f"outside the robot's limits: {exc}", file=file) from None


def check_motion(robot: Robot, motion: Motion, period_s: float, block_s: float = 10.0) -> None:
    """Check the whole motion (approach, excitation, retreat) at the cycle times, jerk included.

    The jerk is the difference of consecutive sampled accelerations over the period (never above
    the true jerk). Sampled in blocks so that a long motion needs no array of every sample.

    Raises
    ------
    TrajectoryError
        Naming the joint, the limit and the time.
    """
    n = int(np.floor(motion.duration_s / period_s)) + 1
    step = max(2, int(block_s / period_s))
    for start in range(0, n, step):
        # one sample of overlap so that the jerk between blocks is checked too
        idx = np.arange(max(start - 1, 0), min(n, start + step))
        t = idx * period_s
        q, qd, qdd = motion.sample(t)
        jerk = np.diff(qdd, axis=0) / period_s if len(t) > 1 else None
        check_limits(robot, q, qd, qdd, label="motion", times=t)
        if jerk is not None:
            check_limits(robot, q[1:], qd[1:], qdd[1:], jerk, label="motion", times=t[1:])
