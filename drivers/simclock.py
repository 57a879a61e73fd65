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
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from drivegain.drivers.objects import EmcyCode
from drivegain.drivers.simtime import LockstepClock

if TYPE_CHECKING:
    from drivegain.drivers.sim import SimulatedCell
    from drivegain.drivers.simdrive import SimDrive

logger = logging.getLogger(__name__)

#: Realtime clock: the integrator thread wakes up about this often (s).
INTEGRATOR_WAKE_S = 0.001


class WallTimer:
    """One thread running scheduled actions (heartbeats, late TPDOs) at monotonic times."""

    def __init__(self, guard: Callable[..., None]):
        self._guard = guard
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
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
                while not self._stopped:
                    now = time.monotonic()
                    if self._heap and self._heap[0][0] <= now:
                        break
                    self._cond.wait(self._heap[0][0] - now if self._heap else None)
                if self._stopped:
                    return
                _, _, fn = heapq.heappop(self._heap)
            self._guard(fn)


class Integrator:
    """Realtime clock: integrates the physics step by step as wall time passes, like a drive's
    own control loop, when no SYNC has done so ahead (see :meth:`SimulatedCell._sync`). Sleeping
    between steps hands the GIL to the bus threads at once."""

    def __init__(self, cell: SimulatedCell):
        self._cell = cell
        self._stopped = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name="drivegain-sim-integrator", daemon=True
        )

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stopped.set()
        if self._thread.is_alive():
            self._thread.join(2.0)

    def _run(self) -> None:
        cell = self._cell
        dt = cell.dt
        # Wake-ups cost CPU: integrate about a millisecond at a time.
        batch = max(1, round(INTEGRATOR_WAKE_S / dt))
        while not self._stopped.is_set():
            cell.guard(cell.catch_up)
            # Nothing powered: integration is free, wake up rarely.
            idle = not cell.physics.any_powered
            due = cell._t0 + (cell.physics.step_index + batch) * dt
            pause = 0.005 if idle else due - time.monotonic()
            if pause > 0:
                self._stopped.wait(pause)


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
