"""Raw CAN traces beside the MCAP log, with python-can's own loggers.

The trace listens on a bus handle of its own, opened with the run's bus configuration, like
``candump`` beside the application: the kernel (SocketCAN) and python-can's virtual bus deliver
every frame on the channel to every other handle, the master's own SYNC, RPDOs and SDO requests
included, stamped on reception. Nothing in the cycle path changes when a trace is on.

The format follows the file suffix, as :class:`can.Logger` chooses it: ``.blf`` (Vector binary),
``.asc`` (Vector ASCII), ``.log`` (candump ``-L``), ``.csv``, ``.mf4`` where its library is
installed. Recorded by a separate reader thread (a :class:`can.Notifier`), never by the bus reader
of the master.

A run's trace is named by ``--can-trace`` (a path as given, relative to the working directory)
or, without it, by ``[acquisition] can_trace`` in the acquisition TOML. The configured name is a
trace *beside each log*: a relative path is relative to the folder of the run's ``.mcap`` (the
daemon's ``output_dir``, or the folder of ``--out``), and ``{log}`` in it stands for the log's name
without ``.mcap`` so that every run gets its own trace (``can_trace = "{log}.blf"``). A fixed name
such as ``"run.blf"`` serves one run: the next is refused before boot (a trace is never
overwritten).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can

from drivegain.drivers.bus import BusConfig, open_bus
from drivegain.errors import BusError, InputError

log = logging.getLogger(__name__)

#: Trace formats python-can writes, by suffix (what :class:`can.Logger` accepts here).
TRACE_SUFFIXES = (".blf", ".asc", ".log", ".csv", ".trc")
#: Stands for the log's file name without ``.mcap`` in a configured trace name.
LOG_PLACEHOLDER = "{log}"


def trace_name_problem(name: Path) -> str | None:
    """Why a configured ``can_trace`` cannot name a trace (unknown suffix), or ``None``."""
    if name.suffix.lower() not in TRACE_SUFFIXES:
        return f"unknown trace format {name.suffix!r}: use one of {', '.join(TRACE_SUFFIXES)}"
    return None


def run_trace_path(given: Path | None, configured: Path | None, log: Path) -> Path | None:
    """The trace file of one run: the command line's, else the configuration's, else none.

    Parameters
    ----------
    given
        ``--can-trace`` (used as given: relative to the working directory, like ``--out``).
    configured
        ``[acquisition] can_trace``: relative to the folder of ``log``; ``{log}`` is replaced by
        the log's name without its suffix; ``~`` is the user's home.
    log
        The run's ``.mcap`` log.
    """
    if given is not None:
        return given
    if configured is None:
        return None
    name = Path(str(configured).replace(LOG_PLACEHOLDER, log.stem)).expanduser()
    return name if name.is_absolute() else log.parent / name


def check_trace_path(path: Path) -> Path:
    """Refuse a trace file name whose suffix selects no python-can logger, or that exists.

    Raises
    ------
    InputError
        Naming the file and ``can_trace``.
    """
    problem = trace_name_problem(path)
    if problem is not None:
        raise InputError(problem, file=path, key="can_trace")
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
    writer = _TraceWriter(logger)
    notifier = can.Notifier(bus, [writer], timeout=0.05)
    try:
        yield
    finally:
        notifier.stop()  # stops its listeners too: the logger flushes and closes the file
        bus.shutdown()
        if writer.failed:
            log.error(
                "CAN trace %s: %d frames could not be written (first: %s)",
                path,
                writer.failed,
                writer.first_error,
            )


#: Largest channel number the binary formats store (BLF: 16 bits).
_MAX_CHANNEL_NUMBER = 0xFFFF


class _TraceWriter(can.Listener):
    """Hands every frame to a python-can logger; a frame it cannot write is counted, not fatal.

    python-can's writers number a channel by the digits its name ends with (``vcan0`` is 0):
    a channel name ending in a large number (a socket path, a generated test channel) does not
    fit BLF's 16-bit field, so such a frame is written without its channel instead of failing.
    A failure of the trace never reaches the run (the trace is a side record); it is reported
    when the trace closes.
    """

    def __init__(self, logger: can.Listener):
        self.logger = logger
        self.failed = 0
        self.first_error = ""
        # per channel name, once: this thread must keep up with the bus (see the module notes)
        self._numbered: dict[object, bool] = {}

    def on_message_received(self, msg: can.Message) -> None:
        fits = self._numbered.get(msg.channel)
        if fits is None:
            number = can.util.channel2int(msg.channel)
            fits = self._numbered[msg.channel] = number is None or number <= _MAX_CHANNEL_NUMBER
        if not fits:
            msg.channel = None  # this handle's own frame object: nobody else reads it
        try:
            self.logger.on_message_received(msg)
        except Exception as exc:
            self.failed += 1
            if not self.first_error:
                self.first_error = repr(exc)

    def stop(self) -> None:
        """Flush and close the trace file."""
        self.logger.stop()


def count_frames(path: Path) -> int:
    """Number of frames in a trace written by :func:`can_trace` (read with python-can)."""
    with can.LogReader(str(path)) as reader:
        return sum(1 for msg in reader if not msg.is_error_frame)
