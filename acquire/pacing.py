"""When to send the next SYNC: absolute deadlines (``realtime``) or at once (``lockstep``).

Realtime deadlines are absolute (``t0 + k·period`` on the monotonic clock), so sleep errors do not
accumulate. A cycle that starts more than a quarter of a period late moves the schedule to the
present: keeping the old one would shorten the next intervals, and a drive in cyclic synchronous
position mode, which reaches each target one period after its SYNC, would fall behind and then
catch up faster than the trajectory (on a trajectory near the velocity limits, a speed fault).
More than one full period late is also counted as an overrun. The lateness that counts is that
of the SYNC itself: the session reports when each SYNC went out (:meth:`Pacer.sync_sent`), so a
delay between the wake-up and the SYNC moves the schedule too.
"""

from __future__ import annotations

import time
from typing import Protocol

from drivegain.acquire.stats import LoopStats


class Pacer(Protocol):
    """Paces the cycle loop and stamps each cycle's log time."""

    def start(self) -> None: ...

    def anchor(self) -> None:
        """The cycles begin now (after the drives were enabled): deadlines count from here."""
        ...

    def wait(self, cycle: int) -> int:
        """Block until cycle ``cycle`` may start; return its log time (ns since the epoch)."""
        ...

    def now_log_ns(self) -> int:
        """The log time of "now" for events between cycles, ns."""
        ...

    def sync_sent(self, cycle: int, monotonic_ns: int) -> None:
        """Cycle ``cycle``'s SYNC went out at ``monotonic_ns``."""
        ...


class LockstepPacer:
    """No waiting: the simulator advances one period per SYNC.

    Log times are simulated: the wall time of the start plus ``cycle · period``, so they are
    evenly spaced and deterministic in the period whatever the machine's speed.
    """

    def __init__(self, period_s: float, stats: LoopStats):
        self.period_ns = round(period_s * 1e9)
        self.stats = stats
        self.epoch_ns = 0
        self._cycle = 0

    def start(self) -> None:
        self.epoch_ns = time.time_ns()

    def anchor(self) -> None:
        pass  # no deadlines

    def wait(self, cycle: int) -> int:
        self._cycle = cycle
        return self.epoch_ns + cycle * self.period_ns

    def now_log_ns(self) -> int:
        return self.epoch_ns + self._cycle * self.period_ns

    def sync_sent(self, cycle: int, monotonic_ns: int) -> None:
        pass  # simulated time: a SYNC is never late


class RealtimePacer:
    """Absolute deadlines on the monotonic clock, log times on the wall clock.

    Parameters
    ----------
    period_s
        SYNC period, s.
    stats
        Receives the wake-up lateness of every cycle and the overrun count.
    spin_s
        The last ``spin_s`` before a deadline are busy-waited rather than slept (0 = sleep only;
        a few hundred µs trade CPU for lower jitter on a loaded machine).
    """

    def __init__(self, period_s: float, stats: LoopStats, spin_s: float = 0.0):
        self.period_ns = round(period_s * 1e9)
        #: Lateness that moves the schedule to the present, ns.
        self.reanchor_ns = self.period_ns // 4
        self.stats = stats
        self.spin_ns = round(spin_s * 1e9)
        self._t0 = 0
        self._offset = 0  # schedule shift from re-anchoring, ns
        self._wall_minus_mono = 0
        self.consecutive_overruns = 0

    def start(self) -> None:
        self._wall_minus_mono = time.time_ns() - time.monotonic_ns()
        self.anchor()

    def anchor(self) -> None:
        # the first deadline one period from now leaves room for the first RPDOs; called again
        # once the drives are enabled, so that the enabling (tens of ms of SDO exchanges) does
        # not make cycle 0 late
        self._t0 = time.monotonic_ns() + self.period_ns
        self._offset = 0

    def deadline_ns(self, cycle: int) -> int:
        """Monotonic deadline of ``cycle``, ns."""
        return self._t0 + cycle * self.period_ns + self._offset

    def wait(self, cycle: int) -> int:
        deadline = self.deadline_ns(cycle)
        now = time.monotonic_ns()
        remaining = deadline - now - self.spin_ns
        if remaining > 0:
            time.sleep(remaining / 1e9)
        if self.spin_ns:
            while time.monotonic_ns() < deadline:
                pass
        now = time.monotonic_ns()
        late = now - deadline
        if late > self.period_ns:
            self.stats.overruns += 1
            self.consecutive_overruns += 1
        else:
            self.consecutive_overruns = 0
        self._reanchor(late)
        self.stats.wake_late.add(late)
        return now + self._wall_minus_mono

    def sync_sent(self, cycle: int, monotonic_ns: int) -> None:
        """Move the schedule if the SYNC itself went out late (after an on-time wake-up)."""
        self._reanchor(monotonic_ns - self.deadline_ns(cycle))

    def _reanchor(self, late: int) -> None:
        if late > self.reanchor_ns:
            # this cycle is on time from now on; the next one a full period later
            self._offset += late

    def now_log_ns(self) -> int:
        return time.time_ns()
