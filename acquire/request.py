"""A run request, read and checked before the bus is touched: files, label, output, bus load.

Everything here can refuse a request with an :class:`~drivegain.errors.InputError` naming the
file or key, and nothing here writes a file or talks to a drive: a daemon answers a bad ``run``
request at once, and a foreground run fails before booting the cell.

A run's size is bounded explicitly, so that every check (and the log) has a bounded cost: at
most :data:`MAX_PERIODS` periods, :data:`MAX_HARMONICS` harmonics per joint and
:data:`MAX_EXCITATION_S` seconds of excitation. The checks themselves look at one period of the
periodic excitation, whatever the number of periods. They run on a worker thread
(:class:`PrepareJob`) that the caller polls, so a signal or a shutdown is honoured at once and the
checks are abandoned.
"""

from __future__ import annotations

import re
import threading
from dataclasses import dataclass, replace
from pathlib import Path

from drivegain.acquire.cantrace import check_trace_path, run_trace_path
from drivegain.acquire.checks import check_bus_load, check_excitation
from drivegain.acquire.config import AcquisitionConfig
from drivegain.acquire.stop import StopRequest
from drivegain.config.payload import Payload, load_payload
from drivegain.drivers.bus import BusLoad
from drivegain.errors import DataError, InputError, OperatorStop, UsageError
from drivegain.excite.trajectory import ExcitationFile, load_trajectory
from drivegain.fileio import reading

_LABEL = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")

#: Most periods of excitation in one run (as ``drivegain excite --periods``).
MAX_PERIODS = 1000
#: Most harmonics per joint of the excitation (as ``drivegain excite --harmonics``).
MAX_HARMONICS = 50
#: Longest excitation of one run, s (all periods): an identification run lasts minutes; one
#: hour (900 000 cycles at 4 ms) is far beyond any campaign and keeps the log bounded.
MAX_EXCITATION_S = 3600.0


@dataclass(frozen=True)
class RunRequest:
    """What to run: trajectory JSON, log to write (``.mcap``), run label, payload TOML, and
    the raw CAN trace to record beside the log (format by suffix, see
    :mod:`drivegain.acquire.cantrace`)."""

    trajectory: Path
    out: Path
    label: str | None = None
    payload: Path | None = None
    can_trace: Path | None = None


@dataclass(frozen=True)
class PreparedRun:
    """A request whose files were read and checked (nothing written, bus untouched)."""

    request: RunRequest
    label: str
    excitation: ExcitationFile
    payload: Payload | None
    attachments: tuple[tuple[str, str, bytes], ...]
    bus_load: BusLoad
    warnings: tuple[str, ...]


def validate_label(label: str) -> str:
    """A run label usable in a file name.

    Raises
    ------
    InputError
        The label is empty or has characters other than letters, digits, ``_ . -``.
    """
    if not _LABEL.match(label):
        raise InputError(
            f"run label {label!r} must be 1-64 letters, digits, '_', '.' or '-'", key="label"
        )
    return label


def prepare_run(cfg: AcquisitionConfig, request: RunRequest) -> PreparedRun:
    """Read and check everything that does not need the bus; write nothing.

    Raises
    ------
    InputError
        A bad trajectory, payload, output path, trace name or label, or a bus that cannot carry
        the cycle.
    """
    out = request.out
    if out.suffix != ".mcap":
        raise InputError("the log must be a .mcap file", file=out)
    for existing in (out, out.with_name(out.name + ".part")):
        if existing.exists():
            raise InputError("already exists (a log is never overwritten)", file=existing)
    # the command line's trace, else the configuration's beside this log (checked alike)
    trace = run_trace_path(request.can_trace, cfg.can_trace, out)
    if trace is not None:
        check_trace_path(trace)
        request = replace(request, can_trace=trace)
    if out.parent.exists() and not out.parent.is_dir():
        raise InputError("is not a directory", file=out.parent)
    robot = cfg.robot
    traj_bytes = _read_bytes(request.trajectory)
    excitation = load_trajectory(request.trajectory)
    check_run_size(excitation, file=request.trajectory)
    excitation.check_robot(robot)
    check_excitation(robot, excitation.fourier, cfg.period_s, file=request.trajectory)
    payload = None
    attachments: list[tuple[str, str, bytes]] = [
        (cfg.robot_path.name, "application/toml", _read_bytes(cfg.robot_path))
    ]
    if request.payload is not None:
        payload_bytes = _read_bytes(request.payload)
        payload = load_payload(request.payload)
        attachments.append((request.payload.name, "application/toml", payload_bytes))
    attachments.append((request.trajectory.name, "application/json", traj_bytes))
    label = validate_label(request.label or ("loaded" if payload is not None else "unloaded"))
    load, warning = check_bus_load(
        robot.n, cfg.period_s, cfg.bus.bitrate, warn=cfg.bus_load_warn, config=cfg.source
    )
    return PreparedRun(
        request=request,
        label=label,
        excitation=excitation,
        payload=payload,
        attachments=tuple(attachments),
        bus_load=load,
        warnings=(warning,) if warning else (),
    )


def _read_bytes(path: Path) -> bytes:
    with reading(path):
        return path.read_bytes()


def check_run_size(excitation: ExcitationFile, *, file: Path) -> None:
    """Refuse an excitation past the explicit limits of a run (periods, harmonics, duration).

    Raises
    ------
    DataError
        Naming the trajectory file, the key and the limit.
    """
    f = excitation.fourier
    if f.periods > MAX_PERIODS:
        raise DataError(
            f"{f.periods} periods: a run has at most {MAX_PERIODS}", file=file, key="periods"
        )
    if f.harmonics > MAX_HARMONICS:
        raise DataError(
            f"{f.harmonics} harmonics per joint: at most {MAX_HARMONICS}",
            file=file,
            key="fourier.a",
        )
    if f.duration_s > MAX_EXCITATION_S:
        raise DataError(
            f"{f.periods} periods of {f.period_s:g} s make {f.duration_s:g} s of excitation: "
            f"a run lasts at most {MAX_EXCITATION_S:g} s",
            file=file,
            key="periods",
        )


class PrepareJob:
    """:func:`prepare_run` on a worker thread that the caller polls and may abandon.

    The checks write nothing and touch no drive, so abandoning them (a signal, a shutdown) is
    safe: the thread ends on its own within the bounded time of the checks, its result unused.

    Parameters
    ----------
    cfg, request
        As :func:`prepare_run`.
    """

    def __init__(self, cfg: AcquisitionConfig, request: RunRequest):
        self.request = request
        self._result: PreparedRun | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(
            target=self._run, args=(cfg,), name="drivegain-checks", daemon=True
        )
        self._thread.start()

    def _run(self, cfg: AcquisitionConfig) -> None:
        try:
            self._result = prepare_run(cfg, self.request)
        except BaseException as exc:  # handed to the caller's thread by result()
            self._error = exc

    @property
    def done(self) -> bool:
        """The checks are over (passed or refused)."""
        return not self._thread.is_alive()

    def wait(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s; whether the checks are over."""
        self._thread.join(timeout)
        return self.done

    def result(self) -> PreparedRun:
        """The checked request (once :attr:`done`).

        Raises
        ------
        InputError
            What :func:`prepare_run` refused.
        """
        if not self.done:
            raise UsageError("the checks are still running")
        if self._error is not None:
            raise self._error
        assert self._result is not None
        return self._result


def prepare_run_interruptible(
    cfg: AcquisitionConfig,
    request: RunRequest,
    stop: StopRequest,
    *,
    poll_s: float = 0.05,
) -> PreparedRun:
    """:func:`prepare_run`, abandoned as soon as ``stop`` is requested (a signal).

    Raises
    ------
    OperatorStop
        A stop arrived during the checks (nothing written, no drive touched).
    InputError
        As :func:`prepare_run`.
    """
    job = PrepareJob(cfg, request)
    while not job.wait(poll_s):
        if stop.requested:
            raise OperatorStop(f"stopped by {stop.reason} during the checks, before any motion")
    if stop.requested:
        raise OperatorStop(f"stopped by {stop.reason} during the checks, before any motion")
    return job.result()
