"""The realtime integrator when the machine is slower than the wall clock (drivers/simclock.py).

On a fake clock: the physics trails the wall clock by at most MAX_LAG_S; time beyond that is
dropped, counted and logged, and the physics lock is released between bounded chunks, so the
drives keep answering however slow the machine (an emulated guest, a saturated host).
"""

from __future__ import annotations

import logging
import threading

import pytest

from drivegain.acquire.config import load_acquisition_config
from drivegain.config import resource_path
from drivegain.drivers.bus import BusConfig
from drivegain.drivers.physics import MotorMode
from drivegain.drivers.sim import SimulatedCell
from drivegain.drivers.simclock import CATCH_UP_CHUNK_S, MAX_LAG_S, Integrator


class FakeClock:
    """A wall clock that moves only when told to, s."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def realtime_cell(powered: bool = True) -> SimulatedCell:
    """The shipped realtime simulation, not on any bus, its time origin at 0 s."""
    cfg = load_acquisition_config(resource_path("acquire-sim-realtime.toml"))
    assert cfg.simulation is not None
    cell = SimulatedCell(
        cfg.robot, BusConfig(interface="virtual", channel="catchup"), cfg.simulation, cfg.period_s
    )
    cell._t0 = 0.0
    if powered:
        for motor in range(cell.physics.n):
            cell.physics.set_mode(motor, MotorMode.TRACK)
    return cell


def test_a_clock_jump_is_dropped_beyond_the_bound_then_caught_up_in_chunks() -> None:
    cell = realtime_cell()
    clock = FakeClock()
    integ = Integrator(cell, clock)
    ph = cell.physics
    assert integ.max_lag_steps == round(MAX_LAG_S / cell.dt)
    assert integ.chunk_steps == round(CATCH_UP_CHUNK_S / cell.dt)
    clock.t = 10.0  # the machine stalled for 10 s
    wall_steps = round(clock.t / cell.dt)
    integ.step()
    assert integ.drops == 1
    assert integ.dropped_steps == wall_steps - integ.max_lag_steps
    assert integ.dropped_s == pytest.approx(10.0 - MAX_LAG_S)
    assert ph.step_index == integ.chunk_steps  # one bounded chunk per hold of the lock
    assert integ.lag_steps() == integ.max_lag_steps - integ.chunk_steps
    for _ in range(100):
        if integ.lag_steps() == 0:
            break
        integ.step()
    # caught up with the wall clock, less the dropped time, without dropping again
    assert integ.lag_steps() == 0 and integ.drops == 1
    assert ph.step_index + integ.dropped_steps == wall_steps
    integ.step()  # on time: nothing to do
    assert ph.step_index + integ.dropped_steps == wall_steps


def test_nothing_powered_integrates_everything_without_dropping() -> None:
    cell = realtime_cell(powered=False)
    clock = FakeClock()
    integ = Integrator(cell, clock)
    clock.t = 10.0
    integ.step()
    assert integ.drops == 0 and integ.lag_steps() == 0
    assert cell.physics.step_index == round(10.0 / cell.dt)


def test_physics_slower_than_time_runs_in_slow_motion_with_a_bounded_lag(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Each internal step costs three steps of wall time: the lag never exceeds the bound after
    a hold of the lock, the drops are counted and logged (at most once per interval), and the
    physics still advances."""
    cell = realtime_cell()
    clock = FakeClock()
    integ = Integrator(cell, clock)
    ph = cell.physics
    advance = ph.advance

    def slow_advance(steps: int) -> None:
        clock.t += 3 * max(0, steps) * cell.dt
        advance(steps)

    ph.advance = slow_advance  # type: ignore[method-assign]
    clock.t = 0.5
    with caplog.at_level(logging.WARNING, logger="drivegain.drivers.simclock"):
        for _ in range(500):
            integ.step()
            assert integ.lag_steps() <= integ.max_lag_steps + 3 * integ.chunk_steps
        integ.stop()  # never started: only the summary
    assert integ.drops > 10
    assert ph.step_index == 500 * integ.chunk_steps
    # every step of wall time was integrated, dropped or is still to come (to round-off)
    accounted = ph.step_index + integ.dropped_steps + integ.lag_steps()
    assert abs(accounted - clock.t / cell.dt) <= 1.0
    warnings = [r.getMessage() for r in caplog.records]
    assert sum("fell" in w and "behind the wall clock" in w for w in warnings) >= 2
    assert len(warnings) < integ.drops  # rate-limited
    assert f"{integ.drops} times" in warnings[-1]


def test_the_drives_keep_answering_while_the_physics_is_far_behind() -> None:
    """The integrator thread on a clock that runs away (a second per look): another thread
    (a bus callback answering an SDO) still gets the physics lock, again and again."""
    cell = realtime_cell()

    class Runaway:
        t = 0.0

        def __call__(self) -> float:
            self.t += 1.0
            return self.t

    integ = Integrator(cell, Runaway())
    integ.start()
    try:
        served = 0
        for _ in range(20):
            # generous bound: a hung integrator would hold the lock for ever
            assert cell.locked().acquire(timeout=30.0), "the physics lock was never released"
            try:
                served += int(cell.physics.step_index >= 0)
            finally:
                cell.locked().release()
            threading.Event().wait(0.002)
        assert served == 20
    finally:
        integ.stop()
    assert integ.drops > 0
