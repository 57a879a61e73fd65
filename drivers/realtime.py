"""One realtime policy for everything that supervises or simulates drives.

What a process does to keep its cycle on time, in one place: the garbage collector's freeze
(:mod:`.gcfreeze`), an optional CPU affinity and interpreter switch interval, and SCHED_FIFO for
the thread that runs the cycle loop. The acquisition rig owns one :class:`RealtimePolicy` and
enters :meth:`~RealtimePolicy.process` once for its life (boot to close, across every run of a
daemon); a session enters :meth:`~RealtimePolicy.cycle_thread` on its cycle thread for one run;
the simulated drives' child process enters :meth:`~RealtimePolicy.process` for its own life; the
acquisition benchmark uses the same object for its baseline loop.

Scheduling changes are undone on exit (the previous policy and priority, the previous CPU set,
the previous switch interval), so a thread or process goes on as it was: a daemon's main thread
is never left at SCHED_FIFO. A refused SCHED_FIFO (no ``CAP_SYS_NICE``, no ``RLIMIT_RTPRIO``) is
not an error: the cycle runs at normal priority and the caller is told why.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from drivegain.drivers import gcfreeze
from drivegain.errors import ConfigError

log = logging.getLogger(__name__)

#: Highest SCHED_FIFO priority on Linux.
MAX_FIFO_PRIORITY = 99


@dataclass(frozen=True)
class FifoOutcome:
    """What became of a SCHED_FIFO request for a cycle thread.

    Parameters
    ----------
    priority
        The priority asked for; 0 when none was.
    granted
        The thread runs at SCHED_FIFO ``priority``.
    refusal
        Why the system refused it (``granted`` is then False), else None.
    """

    priority: int
    granted: bool
    refusal: str | None = None

    def describe(self) -> str:
        """``not asked``, ``granted`` or ``refused (reason)``, for reports."""
        if self.priority <= 0:
            return "not asked"
        return "granted" if self.granted else f"refused ({self.refusal})"


@dataclass(frozen=True)
class RealtimePolicy:
    """How a process and its cycle thread are scheduled while drives are supervised.

    Parameters
    ----------
    gc_freeze
        Hold the garbage collector's freeze (:mod:`.gcfreeze`) in :meth:`process`: full
        collections then walk only what was allocated since (0.1-0.26 s pauses otherwise,
        longer than a TPDO time-out).
    fifo_priority
        SCHED_FIFO priority of the cycle thread in :meth:`cycle_thread`, 1..99; 0 = off.
    cpus
        CPUs the process runs on in :meth:`process` (``os.sched_setaffinity``); None = leave
        the affinity alone.
    switch_interval_s
        The interpreter's switch interval in :meth:`process` (``sys.setswitchinterval``), s;
        None = leave it (5 ms by default, what the rig keeps: docs/realtime.md). The
        acquisition benchmark's ``--switch-interval-s`` sets it to measure the effect.

    A frozen, picklable value: the simulated drives' child process receives it over its pipe.
    """

    gc_freeze: bool = True
    fifo_priority: int = 0
    cpus: frozenset[int] | None = None
    switch_interval_s: float | None = None

    def __post_init__(self) -> None:
        if not 0 <= self.fifo_priority <= MAX_FIFO_PRIORITY:
            raise ConfigError(
                f"SCHED_FIFO priority must be 0..{MAX_FIFO_PRIORITY}, got {self.fifo_priority}"
            )
        if self.switch_interval_s is not None and not 0.0 < self.switch_interval_s <= 1.0:
            raise ConfigError(
                f"the switch interval must be in (0, 1] s, got {self.switch_interval_s}"
            )
        if self.cpus is not None:
            if not self.cpus:
                raise ConfigError("an empty CPU set would leave the process nowhere to run")
            object.__setattr__(self, "cpus", frozenset(self.cpus))

    @contextmanager
    def process(self) -> Iterator[None]:
        """The process-wide part (garbage-collector freeze, CPU affinity, the interpreter's
        switch interval) inside the block.

        Nests: the freeze is reference-counted (the last exit unfreezes); the affinity and the
        switch interval each block set are restored when it ends. Enter it before starting the
        threads that supervise or simulate drives, as threads started later inherit the
        affinity of their creator.
        """
        saved = _set_affinity(self.cpus) if self.cpus is not None else {}
        switch = sys.getswitchinterval()
        if self.switch_interval_s is not None:
            sys.setswitchinterval(self.switch_interval_s)
        try:
            if self.gc_freeze:
                # one full collection first (if no other hold is in force, so no drive is
                # supervised yet), so that no garbage is frozen
                gcfreeze.hold(collect=True)
            try:
                yield
            finally:
                if self.gc_freeze:
                    gcfreeze.release()
        finally:
            sys.setswitchinterval(switch)
            _restore_affinity(saved)

    @contextmanager
    def cycle_thread(self) -> Iterator[FifoOutcome]:
        """SCHED_FIFO ``fifo_priority`` for the calling thread inside the block.

        Yields
        ------
        FifoOutcome
            Whether it was granted (a refusal is reported, not raised). The thread's previous
            policy and priority are restored when the block ends.
        """
        prio = self.fifo_priority
        if prio <= 0:
            yield FifoOutcome(0, False)
            return
        before = (os.sched_getscheduler(0), os.sched_getparam(0))
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
        except OSError as exc:
            yield FifoOutcome(prio, False, exc.strerror or str(exc))
            return
        try:
            yield FifoOutcome(prio, True)
        finally:
            try:
                os.sched_setscheduler(0, before[0], before[1])
            except OSError as exc:  # never hide the block's own exception
                log.warning("cannot restore the thread's scheduling policy: %s", exc)

    def refreeze(self) -> None:
        """While :meth:`process` is held: freeze what the collector tracks now as well.

        For what lives as long as the hold (a rig's booted master, network and simulated
        drives), which full collections would otherwise walk; not for a run's objects, which a
        freeze would keep until the hold ends (see :func:`.gcfreeze.refreeze`). O(1), no
        collection; does nothing without the freeze.
        """
        if self.gc_freeze:
            gcfreeze.refreeze()


def _set_affinity(cpus: frozenset[int]) -> dict[int, set[int]]:
    """Every thread of this process on ``cpus``; return each thread's previous CPU set."""
    saved: dict[int, set[int]] = {}
    for tid in _threads():
        try:
            saved[tid] = os.sched_getaffinity(tid)
            os.sched_setaffinity(tid, cpus)
        except ProcessLookupError:  # the thread ended meanwhile
            saved.pop(tid, None)
        except OSError:
            _restore_affinity(saved)
            raise
    return saved


def _restore_affinity(saved: dict[int, set[int]]) -> None:
    if not saved:
        return
    # threads started inside the block inherited the policy's set: give them the process's
    fallback = saved.get(os.getpid(), next(iter(saved.values())))
    for tid in _threads():
        try:
            os.sched_setaffinity(tid, saved.get(tid, fallback))
        except OSError as exc:
            if not isinstance(exc, ProcessLookupError):
                log.warning("cannot restore the CPU affinity of thread %d: %s", tid, exc)


def _threads() -> list[int]:
    """Kernel ids of this process's threads (Linux ``/proc/self/task``)."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [0]  # the calling thread only
