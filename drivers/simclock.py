"""The simulated cell's time services: its clock (:class:`CellClock`: simulated in lockstep, the
wall clock otherwise), the realtime integrator, and each drive's heartbeat consumer (0x1016).

A CiA 301 consumer entry (0x1016 sub 1) names a producer node id (bits 16-23) and a time-out in
ms (bits 0-15; 0 or producer 0 = off). Monitoring starts with the first heartbeat received from
that producer after the entry was written; a drive that then hears nothing for the time-out
reports a heartbeat event, which a CiA 402 drive answers with its fault reaction (see
:meth:`~drivegain.drivers.simdrive.SimDrive.heartbeat_lost`).

Time: the cell's clock (:class:`CellClock`). In lockstep the simulated clock it shares with the
master (:mod:`.simtime`): the time-out counts simulated time while the master runs, and follows
the wall clock once the master has left (its SYNCs no longer advance anything). In realtime, and
whenever the drives run in a process of their own, ``time.monotonic``.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from drivegain.drivers.objects import EmcyCode
from drivegain.drivers.simtime import LockstepClock, Schedule, wait_until_due

if TYPE_CHECKING:
    from drivegain.drivers.sim import SimulatedCell
    from drivegain.drivers.simdrive import SimDrive

logger = logging.getLogger(__name__)

#: Realtime clock: the integrator thread wakes up about this often (s).
INTEGRATOR_WAKE_S = 0.001
#: Realtime clock: the most the physics may trail the wall clock, s. A machine too slow for
#: realtime physics (an emulated guest, a saturated host) would otherwise integrate an ever
#: longer backlog under the physics lock, answering no SDO, SYNC or heartbeat meanwhile; beyond
#: this bound the integrator drops the time it cannot catch up (the simulated motion loses it), as
#: a real drive's control loop skips the cycles it overran and keeps answering.
MAX_LAG_S = 0.01
#: Realtime clock: the most simulated time integrated per hold of the physics lock while behind,
#: s, so that the bus threads get the lock in between.
CATCH_UP_CHUNK_S = 0.002
#: Realtime clock: shortest pause between two holds of the physics lock, s (hands the lock and
#: the interpreter to the bus threads even when the physics is behind).
MIN_PAUSE_S = 0.0005
#: Realtime clock: the integrator pauses at least this many times the CPU time its last hold of
#: the lock took, so that it uses at most 1 / (1 + this) of the interpreter. Where the machine
#: keeps pace (integration costs a tenth of the time it covers) this never binds; where it does
#: not, the SYNC handling, which integrates what it needs itself, gets the interpreter first.
DUTY_PAUSE_FACTOR = 3.0
#: Longest pause the duty limit imposes, s.
MAX_DUTY_PAUSE_S = 0.05
#: Realtime clock: at most one warning about dropped time per this interval, s.
DROP_LOG_INTERVAL_S = 5.0


class WallTimer:
    """One thread running scheduled actions (heartbeats, late TPDOs) at monotonic times."""

    def __init__(self, guard: Callable[..., None]):
        self._guard = guard
        self._heap: Schedule = []
        self._cond = threading.Condition()
        self._seq = itertools.count()
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name="drivegain-sim-timer", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def call_at(self, due: float, fn: Callable[[], None]) -> None:
        with self._cond:
            heapq.heappush(self._heap, (due, next(self._seq), fn))
            self._cond.notify()

    def stop(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(2.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                if not wait_until_due(
                    self._cond, self._heap, time.monotonic, lambda: self._stopped
                ):
                    return
                _, _, fn = heapq.heappop(self._heap)
            self._guard(fn)


class Integrator:
    """Realtime clock: integrates the physics step by step as wall time passes, like a drive's
    own control loop, when no SYNC has done so ahead (see :meth:`SimulatedCell._sync`). Sleeping
    between steps hands the GIL to the bus threads at once.

    The physics may trail the wall clock by :data:`MAX_LAG_S` at most: when it falls further
    behind (the machine cannot integrate as fast as time passes), the excess is dropped, by
    moving the cell's time origin (``cell._t0``, which the SYNC handling reads too) forward,
    counted in :attr:`drops` and :attr:`dropped_steps`, and logged. Setpoints, control loops
    and SYNC instants all count the same simulated time, and the drives keep answering; but the
    master's targets still come once per wall-clock period, so a trajectory streamed meanwhile
    is covered in less simulated time (faster, with larger following errors) than planned.

    Parameters
    ----------
    cell
        The cell whose physics to integrate.
    clock
        The wall clock, s (``time.monotonic``; a fake one in tests).
    """

    def __init__(self, cell: SimulatedCell, clock: Callable[[], float] = time.monotonic):
        self._cell = cell
        self._clock = clock
        self._stopped = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name="drivegain-sim-integrator", daemon=True
        )
        dt = cell.dt
        self.max_lag_steps = max(1, round(MAX_LAG_S / dt))
        self.chunk_steps = max(1, round(CATCH_UP_CHUNK_S / dt))
        #: How often, and how many internal steps in all, the physics dropped time.
        self.drops = 0
        self.dropped_steps = 0
        self._logged_at = -math.inf
        self._logged_steps = 0
        self._logged_drops = 0

    @property
    def dropped_s(self) -> float:
        """Simulated time dropped so far, s."""
        return self.dropped_steps * self._cell.dt

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stopped.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        if self.drops:
            logger.warning(
                "simulated drives: the physics fell behind the wall clock %d times; %.3f s of "
                "simulated time dropped in all (the machine was too slow for realtime)",
                self.drops,
                self.dropped_s,
            )

    def lag_steps(self) -> int:
        """Internal steps the physics trails the wall clock by (caller holds the physics lock)."""
        cell = self._cell
        # (a step's worth of round-off after time was dropped: _t0 is no multiple of dt)
        return math.floor((self._clock() - cell._t0) / cell.dt + 1e-6) - cell.physics.step_index

    def bound_lag(self) -> None:
        """Drop the lag beyond :data:`MAX_LAG_S` while a motor is powered (caller holds the
        physics lock; nothing powered, integration is free and nothing is dropped)."""
        if not self._cell.physics.any_powered:
            return
        lag = self.lag_steps()
        if lag > self.max_lag_steps:
            self._drop(lag - self.max_lag_steps)

    def step(self) -> None:
        """Integrate towards the present (caller holds the physics lock): all of it when nothing
        is powered (free), else at most :data:`CATCH_UP_CHUNK_S`, after dropping the lag beyond
        :data:`MAX_LAG_S`."""
        self.bound_lag()
        lag = self.lag_steps()
        if lag <= 0:
            return
        ph = self._cell.physics
        if ph.any_powered:
            lag = min(lag, self.chunk_steps)
        ph.advance(lag)

    def _drop(self, steps: int) -> None:
        cell = self._cell
        cell._t0 += steps * cell.dt
        self.drops += 1
        self.dropped_steps += steps
        now = self._clock()
        if now - self._logged_at >= DROP_LOG_INTERVAL_S:
            logger.warning(
                "simulated drives: the physics fell %.0f ms behind the wall clock; dropped "
                "%.3f s of simulated time in %d drops since the last report (%.3f s in all), "
                "the drives keep answering",
                (steps + self.max_lag_steps) * cell.dt * 1e3,
                (self.dropped_steps - self._logged_steps) * cell.dt,
                self.drops - self._logged_drops,
                self.dropped_s,
            )
            self._logged_at = now
            self._logged_steps = self.dropped_steps
            self._logged_drops = self.drops

    def _run(self) -> None:
        cell = self._cell
        dt = cell.dt
        # Wake-ups cost CPU: integrate about a millisecond at a time.
        batch = max(1, round(INTEGRATOR_WAKE_S / dt))
        while not self._stopped.is_set():
            cpu = time.thread_time()
            cell.guard(self.step)
            cpu = time.thread_time() - cpu
            # Nothing powered: integration is free, wake up rarely.
            idle = not cell.physics.any_powered
            due = cell._t0 + (cell.physics.step_index + batch) * dt
            pause = 0.005 if idle else due - self._clock()
            # Always pause a little: behind, the next chunk waits for the bus threads' turn.
            floor = max(MIN_PAUSE_S, min(DUTY_PAUSE_FACTOR * cpu, MAX_DUTY_PAUSE_S))
            self._stopped.wait(max(pause, floor))


class CellClock:
    """What the simulated drives read the time from and schedule on.

    Parameters
    ----------
    guard
        Runs a scheduled action with the cell's physics lock, recording its exceptions.
    lockstep
        The simulated clock shared with the master, or None for the wall clock.
    """

    def __init__(self, guard: Callable[..., None], lockstep: LockstepClock | None):
        self._guard = guard
        self.lockstep = lockstep
        self._timer: WallTimer | None = None

    def start(self) -> None:
        if self.lockstep is None:
            self._timer = WallTimer(self._guard)
            self._timer.start()

    def stop(self) -> None:
        if self._timer is not None:
            self._timer.stop()
            self._timer = None
        if self.lockstep is not None:
            self.lockstep.close()

    @property
    def running(self) -> bool:
        return self._timer is not None or self.lockstep is not None

    def now(self) -> float:
        """The present, s (simulated in lockstep, else ``time.monotonic()``)."""
        return self.lockstep.now() if self.lockstep is not None else time.monotonic()

    def stamp(self, timestamp: float) -> float:
        """When a frame received with bus time stamp ``timestamp`` was sent, on this clock."""
        if self.lockstep is not None:  # see LockstepClock.stamp
            return min(timestamp, self.lockstep.now())
        return time.monotonic()

    def call_at(self, due: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` (guarded) at ``due`` on this clock."""
        if self.lockstep is not None:
            self.lockstep.call_at(due, lambda: self._guard(fn))
        elif self._timer is not None:
            self._timer.call_at(due, fn)


class HeartbeatConsumer:
    """0x1016 sub 1 of one simulated drive.

    Parameters
    ----------
    drive
        The drive whose fault reaction a time-out starts.
    clock
        The cell's clock.
    """

    def __init__(self, drive: SimDrive, clock: CellClock):
        self.drive = drive
        self.clock = clock
        self.producer = 0
        self.timeout_s = 0.0
        self._generation = 0
        self.expired = False

    @property
    def active(self) -> bool:
        """An entry is configured."""
        return self.producer != 0 and self.timeout_s > 0.0

    def configure(self, entry: int) -> None:
        """A new 0x1016 sub 1 value: monitoring waits for the producer's next heartbeat."""
        self.producer = (entry >> 16) & 0x7F
        self.timeout_s = (entry & 0xFFFF) / 1000.0
        self._generation += 1
        self.expired = False

    def on_heartbeat(self, sent: float) -> None:
        """A heartbeat of the producer, sent at ``sent`` (the cell's clock): re-arm."""
        if not self.active:
            return
        self._generation += 1
        generation = self._generation
        self.clock.call_at(sent + self.timeout_s, lambda: self._expire(generation))

    def _expire(self, generation: int) -> None:
        """Consumer time-out (CiA 301 heartbeat event): EMCY 0x8130 and the fault reaction, a
        quick stop ramp for a powered motor, then FAULT with the brake on."""
        drive = self.drive
        if generation != self._generation or not self.active or drive.never_boots:
            return
        self.expired = True
        logger.warning(
            "simulated drive %d: heartbeat consumer time-out: no heartbeat of node %d for "
            "%d ms: fault reaction (quick stop if powered, then disable), EMCY 0x%04X",
            drive.node_id,
            self.producer,
            round(self.timeout_s * 1000),
            int(EmcyCode.HEARTBEAT),
        )
        drive.inject_fault(int(EmcyCode.HEARTBEAT), emcy=True, ramp=True)
