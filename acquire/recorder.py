"""The recorder: a writer thread that streams cycles and events from a bounded queue to the log.

The cycle loop only enqueues; encoding, compression and disk writes happen on this thread (never on
the CAN notifier thread, never on the cycle thread). The queue is bounded, so memory stays bounded
whatever the run length: in ``lockstep`` the producer simply waits when the queue is full (time is
simulated), in ``realtime`` a full queue means the disk cannot keep up and the run is stopped
rather than silently dropping cycles (:class:`RecorderOverrun`).

About once a second the writer is flushed and fsynced (``LogWriter.flush``), so a process killed
with SIGKILL leaves a ``.part`` file holding every complete chunk up to the last second.
"""

from __future__ import annotations

import logging
import math
import queue
import re
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from drivegain.errors import DrivegainError, InputError, UsageError
from drivegain.formats.log import JOINT_STATES
from drivegain.lifecycle import release_quietly

log = logging.getLogger(__name__)


class RecorderError(DrivegainError):
    """Writing the log failed (disk full, I/O error): the run cannot continue safely."""


class RecorderOverrun(RecorderError):
    """The recorder queue is full in ``realtime``: the disk does not keep up with the bus."""


class LogSink(Protocol):
    """What the recorder needs from :class:`drivegain.formats.logwriter.LogWriter`."""

    def write_joint_state(
        self,
        *,
        cycle: int,
        t: float,
        log_time_ns: int,
        position: Any,
        current_reference: Any,
        current: Any,
        setpoint: Any,
    ) -> None: ...

    def write_raw(self, *, cycle: int, log_time_ns: int, raw: Mapping[str, Any]) -> None: ...

    def write_event(
        self,
        *,
        log_time_ns: int,
        level: str,
        node: int | None,
        code: int | None,
        text: str,
        **fields: Any,
    ) -> None: ...

    def flush(self) -> None: ...

    def finish(self) -> Path: ...

    def close_unfinished(self) -> None: ...


@dataclass(frozen=True, slots=True)
class CycleRecord:
    """One SYNC cycle as it goes to ``/joint_states`` and ``/drives/raw``.

    Arrays are joint-side: positions and setpoints in rad, currents in A.
    """

    cycle: int
    t: float
    log_time_ns: int
    position: np.ndarray
    current_reference: np.ndarray
    current: np.ndarray
    setpoint: np.ndarray
    raw: Mapping[str, Any]


@dataclass(frozen=True, slots=True)
class EventRecord:
    """One ``/events`` message: ``level`` is ``info``, ``warning``, ``error`` or ``fault``."""

    log_time_ns: int
    level: str
    text: str
    node: int | None = None
    code: int | None = None
    fields: Mapping[str, Any] = field(default_factory=dict)


_STOP = object()
#: A decimal number as text ("802", "-1.5", "2e-05"); hex, "nan" and "inf" do not match.
_NUMBER = re.compile(r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][-+]?[0-9]+)?")


def typed_fields(fields: Mapping[str, Any]) -> dict[str, Any]:
    """Event fields with decimal text turned into JSON numbers.

    The cycle statistics and some callers format their values as text (for the daemon's status
    reply); in the log a number is a number, so tools can plot and filter it. Integers stay
    integers; other text (node lists, reasons, state names) is kept as it is.
    """
    out: dict[str, Any] = {}
    for key, value in fields.items():
        if isinstance(value, str) and _NUMBER.fullmatch(value):
            number: int | float
            if any(c in value for c in ".eE"):
                number = float(value)
                out[key] = number if math.isfinite(number) else value
            else:
                out[key] = int(value)
        else:
            out[key] = value
    return out


class Recorder:
    """Writer thread between the cycle loop and a :class:`LogSink`.

    Parameters
    ----------
    sink
        The open log (a ``LogWriter``); the recorder owns it from :meth:`start` on and finishes it.
    capacity
        Queue length in records (cycles + events); bounds the memory held in flight.
    flush_interval_s
        How often the log is flushed and fsynced, s.
    """

    def __init__(self, sink: LogSink, *, capacity: int = 4096, flush_interval_s: float = 1.0):
        if capacity < 1:
            raise UsageError("capacity must be >= 1")
        self._sink = sink
        self._queue: queue.Queue[object] = queue.Queue(maxsize=capacity)
        self._interval = float(flush_interval_s)
        self._thread = threading.Thread(target=self._run, name="drivegain-recorder", daemon=True)
        self._error: BaseException | None = None
        self._closed = False
        self.capacity = capacity
        self.written_cycles = 0
        self.written_events = 0
        self.flushes = 0
        self.high_water = 0

    # -- producer side (the cycle thread) -------------------------------------------------------

    def start(self) -> None:
        """Start the writer thread."""
        self._thread.start()

    @property
    def closed(self) -> bool:
        """:meth:`finish` or :meth:`abandon` was called."""
        return self._closed

    @property
    def failed(self) -> BaseException | None:
        """The exception that stopped the writer, if any."""
        return self._error

    def put_cycle(self, record: CycleRecord, *, block: bool) -> None:
        """Queue one cycle.

        Parameters
        ----------
        block
            Wait for room when the queue is full (``lockstep``); otherwise a full queue raises.

        Raises
        ------
        RecorderOverrun
            The queue is full and ``block`` is false.
        RecorderError
            The writer thread has failed.
        """
        self._check()
        if block:
            self._put_blocking(record)
        else:
            try:
                self._queue.put_nowait(record)
            except queue.Full:
                raise RecorderOverrun(
                    f"recorder queue full ({self.capacity} records): the log cannot keep up "
                    f"at cycle {record.cycle}"
                ) from None
        size = self._queue.qsize()
        if size > self.high_water:
            self.high_water = size

    def put_event(self, record: EventRecord) -> None:
        """Queue one event; waits for room (events are rare and must never be lost)."""
        self._check()
        self._put_blocking(record)

    def _put_blocking(self, item: object) -> None:
        while True:
            try:
                self._queue.put(item, timeout=0.2)
                return
            except queue.Full:
                # the writer may have died while we waited: do not wait forever for it
                self._check()

    def _check(self) -> None:
        if self._closed:
            raise RecorderError("the recorder is closed")
        if self._error is not None:
            raise RecorderError(f"writing the log failed: {self._error}") from self._error
        if self._thread.ident is not None and not self._thread.is_alive():
            raise RecorderError("the recorder thread has stopped")

    # -- end of run ----------------------------------------------------------------------------

    def finish(self) -> Path:
        """Write everything queued, finish the log (``.part`` renamed) and return its path.

        Raises
        ------
        RecorderError
            Writing failed; the log is left as ``.part`` with what could be written.
        """
        self._stop_thread()
        if self._error is not None:
            self._sink.close_unfinished()
            raise RecorderError(f"writing the log failed: {self._error}") from self._error
        try:
            return self._sink.finish()
        except Exception as exc:
            self._sink.close_unfinished()
            raise RecorderError(f"finishing the log failed: {exc}") from exc

    def abandon(self) -> None:
        """Write what is queued and close without finishing (the ``.part`` file stays)."""
        self._stop_thread()
        # on the way down: report, never raise
        release_quietly(self._sink.close_unfinished, "closing the unfinished log", log)

    def _stop_thread(self) -> None:
        if self._closed:
            raise RecorderError("the recorder is already closed")
        self._closed = True
        if self._thread.ident is None:
            return
        while self._thread.is_alive():
            try:
                self._queue.put(_STOP, timeout=0.2)
                break
            except queue.Full:
                continue
        self._thread.join()

    # -- writer thread -------------------------------------------------------------------------

    def _run(self) -> None:
        next_flush = time.monotonic() + self._interval
        while True:
            timeout = max(0.0, next_flush - time.monotonic())
            try:
                item = self._queue.get(timeout=timeout)
            except queue.Empty:
                item = None
            if item is _STOP:
                break
            if item is not None and self._error is None:
                try:
                    self._write(item)
                except BaseException as exc:
                    log.error("log write failed: %s", exc)
                    self._error = exc
            if time.monotonic() >= next_flush:
                next_flush = time.monotonic() + self._interval
                if self._error is None:
                    try:
                        self._sink.flush()
                        self.flushes += 1
                    except BaseException as exc:
                        log.error("log flush failed: %s", exc)
                        self._error = exc

    def _write(self, item: object) -> None:
        if isinstance(item, CycleRecord):
            self._sink.write_joint_state(
                cycle=item.cycle,
                t=item.t,
                log_time_ns=item.log_time_ns,
                position=item.position,
                current_reference=item.current_reference,
                current=item.current,
                setpoint=item.setpoint,
            )
            self._sink.write_raw(cycle=item.cycle, log_time_ns=item.log_time_ns, raw=item.raw)
            self.written_cycles += 1
        elif isinstance(item, EventRecord):
            self._sink.write_event(
                log_time_ns=item.log_time_ns,
                level=item.level,
                node=item.node,
                code=item.code,
                text=item.text,
                **typed_fields(item.fields),
            )
            self.written_events += 1
        else:  # pragma: no cover - only this module queues items
            raise TypeError(f"unexpected record {type(item).__name__}")


def part_path(out: Path) -> Path:
    """The file a run is written to until it is finished (``NAME.mcap.part``)."""
    return out.with_name(out.name + ".part")


def holds_cycles(part: Path) -> bool:
    """Whether an unfinished log holds at least one recorded cycle (read up to the first one).

    A file cut anywhere counts what it holds before the cut; an empty or unreadable one holds
    nothing.
    """
    try:
        if part.stat().st_size == 0:
            return False
        from drivegain.formats.logreader import iter_channel

        for _ in iter_channel(part, JOINT_STATES):
            return True
    except (OSError, DrivegainError, ValueError):
        pass  # what could be read held no cycle
    return False


def discard_unrecorded(out: Path) -> bool:
    """Remove the ``.part`` of a failed run when it holds no recorded cycle; whether it did.

    Such a file (a log that could not even be started, e.g. on a full disk) would only block
    the retry (a log is never overwritten); one holding cycles is kept, whatever its state.
    """
    part = part_path(out)
    if not part.exists() or holds_cycles(part):
        return False
    try:
        part.unlink()
    except OSError as exc:
        log.error("cannot remove %s: %s", part, exc.strerror)
        return False
    log.info("removed %s: nothing was recorded", part)
    return True


def unwritable_log(exc: OSError, out: Path) -> InputError:
    """The one-line error of a log that could not be written before anything was recorded.

    Parameters
    ----------
    exc
        What the file system said (e.g. ENOSPC).
    out
        The run's log (``NAME.mcap``); the message names the file being written.
    """
    where = exc.filename or part_path(out)
    return InputError(
        f"cannot write the log ({exc.strerror or exc}): nothing was recorded, no drive moved",
        file=where,
    )
