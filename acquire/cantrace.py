"""Raw CAN traces beside the MCAP log, with python-can's own loggers.

The trace listens on a bus handle of its own, opened with the run's bus configuration, like
``candump`` beside the application: the kernel (SocketCAN) and python-can's virtual bus deliver
every frame on the channel to every other handle, the master's own SYNC, RPDOs and SDO requests
included, stamped on reception. Nothing in the cycle path changes when a trace is on.

The format follows the file suffix, as :class:`can.Logger` chooses it: ``.blf`` (Vector binary),
``.asc`` (Vector ASCII), ``.log`` (candump ``-L``), ``.csv``, ``.mf4`` where its library is
installed. Recorded by a separate reader thread (a :class:`can.Notifier`), never by the bus reader
of the master.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can

from drivegain.drivers.bus import BusConfig, open_bus
from drivegain.errors import BusError, InputError

#: Trace formats python-can writes, by suffix (what :class:`can.Logger` accepts here).
TRACE_SUFFIXES = (".blf", ".asc", ".log", ".csv", ".trc")


def check_trace_path(path: Path) -> Path:
    """Refuse a trace file name whose suffix selects no python-can logger, or that exists.

    Raises
    ------
    InputError
        Naming the file and ``can_trace``.
    """
    if path.suffix.lower() not in TRACE_SUFFIXES:
        raise InputError(
            f"unknown trace format {path.suffix!r}: use one of {', '.join(TRACE_SUFFIXES)}",
            file=path,
            key="can_trace",
        )
    if path.exists():
        raise InputError("exists; refusing to overwrite it", file=path, key="can_trace")
    return path


@contextmanager
def can_trace(bus_cfg: BusConfig, path: Path | None) -> Iterator[None]:
    """Record every frame on the bus of ``bus_cfg`` into ``path`` while the block runs.

    Parameters
    ----------
    bus_cfg
        The run's bus; a second handle on the same channel is opened for the trace.
    path
        The trace file (format by suffix), or ``None`` for no trace (the block just runs).

    Raises
    ------
    BusError
        The trace's bus handle cannot be opened.
    """
    if path is None:
        yield
        return
    bus = open_bus(bus_cfg)
    try:
        logger = can.Logger(str(path))
    except Exception as exc:
        bus.shutdown()
        raise BusError(f"cannot write the CAN trace {path}: {exc}") from None
    notifier = can.Notifier(bus, [logger], timeout=0.05)
    try:
        yield
    finally:
        notifier.stop()  # stops its listeners too: the logger flushes and closes the file
        bus.shutdown()


def count_frames(path: Path) -> int:
    """Number of frames in a trace written by :func:`can_trace` (read with python-can)."""
    with can.LogReader(str(path)) as reader:
        return sum(1 for msg in reader if not msg.is_error_frame)
