"""Checks made before any motion: the bus load of the cycle and the motion against the limits."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drivegain.config.robot import Robot
from drivegain.drivers.bus import BusLoad, bus_load
from drivegain.errors import ConfigError, DataError, TrajectoryError
from drivegain.excite.limits import check_limits
from drivegain.excite.motion import Motion, Phase
from drivegain.excite.motion import check_excitation as check_series
from drivegain.formats.fourier import FourierTrajectory

#: Most work of one sampled check of a period (samples times 1 + 2H basis columns): about a
#: second on a busy machine; a longer period is sampled more coarsely (the rigorous bound of
#: :func:`~drivegain.excite.limits.fourier_usage` covers it between samples).
SAMPLE_BUDGET = 2_000_000
#: Samples evaluated at once (bounds memory).
BLOCK = 20_000


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
    """Check the excitation against every limit over one period (it is periodic).

    First the rigorous bound over continuous time (the check the planner makes after boot,
    :func:`drivegain.excite.motion.check_excitation`, here before it); only when that refuses,
    one period is sampled (at 1 kHz or faster, coarser past :data:`SAMPLE_BUDGET`) to name the
    joint and the time of a violation. The work is bounded whatever the number of periods.

    Raises
    ------
    DataError
        Naming the trajectory file and the joint and limit violated.
    """
    try:
        check_series(robot, fourier)
    except TrajectoryError as bound:
        try:
            _sample_one_period(robot, fourier, period_s)
        except TrajectoryError as exc:
            raise DataError(f"outside the robot's limits: {exc}", file=file) from None
        raise DataError(f"outside the robot's limits: {bound}", file=file) from None


def _sample_one_period(robot: Robot, fourier: FourierTrajectory, period_s: float) -> None:
    dt = min(period_s, 1e-3)
    n = int(np.ceil(fourier.period_s / dt)) + 1
    n = min(n, max(2, SAMPLE_BUDGET // (1 + 2 * fourier.harmonics)))
    t_all = np.linspace(0.0, fourier.period_s, n)
    for start in range(0, n, BLOCK):
        t = t_all[start : start + BLOCK]
        q, qd, qdd, qddd = fourier.evaluate(t)
        check_limits(robot, q, qd, qdd, qddd, label="excitation", times=t)


def check_motion(robot: Robot, motion: Motion, period_s: float, block_s: float = 10.0) -> None:
    """Check the motion (approach, excitation, retreat) at the cycle times, jerk included.

    The jerk is the difference of consecutive sampled accelerations over the period (never above
    the true jerk). The ruckig segments (and any other) are checked whole; the excitation is
    periodic, so one period of it is checked (from the join with the approach), plus its last
    cycles into the retreat: the work is bounded however many periods the run has. Beyond
    :data:`SAMPLE_BUDGET` samples of one period, the rest of it is covered by the rigorous
    continuous-time bound the planner checked. Sampled in blocks (bounded memory).

    Raises
    ------
    TrajectoryError
        Naming the joint, the limit and the time.
    """
    step = max(2, int(block_s / period_s))
    for first, last in _cycle_ranges(motion, period_s):
        for start in range(first, last + 1, step):
            # one sample of overlap so that the jerk between blocks is checked too
            idx = np.arange(max(start - 1, first), min(last + 1, start + step))
            t = idx * period_s
            q, qd, qdd = motion.sample(t)
            check_limits(robot, q, qd, qdd, label="motion", times=t)
            if len(t) > 1:
                jerk = np.diff(qdd, axis=0) / period_s
                check_limits(robot, q[1:], qd[1:], qdd[1:], jerk, label="motion", times=t[1:])


def _cycle_ranges(motion: Motion, period_s: float) -> list[tuple[int, int]]:
    """Inclusive ranges of cycle indices to check, merged, in time order."""
    last_cycle = int(np.floor(motion.duration_s / period_s)) + 1
    ranges: list[tuple[int, int]] = []
    for phase, t0, seg in motion.segments:
        t1 = t0 + seg.duration
        if phase is Phase.EXCITATION and motion.fourier is not None:
            harmonics = motion.fourier.harmonics
            budget_s = SAMPLE_BUDGET // (1 + 2 * harmonics) * period_s
            window = min(seg.duration, motion.fourier.period_s + 2 * period_s, budget_s)
            spans = [(t0, t0 + window), (max(t0, t1 - 4 * period_s), t1)]
        else:
            spans = [(t0, t1)]
        for a, b in spans:
            # a cycle before and after: the jerk across each join is checked too
            lo = max(0, int(np.floor(a / period_s)) - 1)
            hi = min(last_cycle, int(np.ceil(b / period_s)) + 1)
            ranges.append((lo, hi))
    ranges.sort()
    merged: list[tuple[int, int]] = []
    for lo, hi in ranges:
        if merged and lo <= merged[-1][1] + 1:
            merged[-1] = (merged[-1][0], max(merged[-1][1], hi))
        else:
            merged.append((lo, hi))
    return merged
