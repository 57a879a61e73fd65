"""Read and prepare the runs of an identification, in worker processes when they are long.

Reading a log and preparing it (filters, regressor, decimation) is most of an identification's
time for long recordings, and each run is independent of the others. When the logs together
exceed :data:`PARALLEL_BYTES`, each run is read and prepared in a forked worker process, one per
CPU at most; otherwise, or where forking is not safe (no ``fork``, other threads running), one
after the other in this process. Both ways run the same function on the same data, so the
results are identical.

A worker sends its progress, then the prepared run over a pipe: the small fields pickled, the
regressor's series (about a hundred MB for a 10-minute 1 kHz log) as raw bytes read straight
into an array of this process, so they are never held twice. An error in a worker (a corrupt
log) comes back as the same exception, file and key included; a worker that dies is reported by
run.
"""

from __future__ import annotations

import dataclasses
import functools
import multiprocessing
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from drivegain.config.payload import Payload
from drivegain.config.robot import WristFriction
from drivegain.dynamics.model import RobotModel
from drivegain.errors import IdentificationError, InputError
from drivegain.formats.trajectory import attached_fourier
from drivegain.identify.blas import limited_blas_threads
from drivegain.identify.columns import bases_for_forms, stored_columns
from drivegain.identify.forked import fork_is_safe, send_error
from drivegain.identify.prepare import PreparedRun, prepare_recording
from drivegain.identify.report import RunInfo
from drivegain.identify.runs import LoadedRun, load_run
from drivegain.identify.signal import FilterSettings, default_filter
from drivegain.identify.signchoice import at_position_cutoff

if TYPE_CHECKING:
    from rich.progress import Progress

    from drivegain.identify.pipeline import IdentifyRequest

__all__ = ["PARALLEL_BYTES", "Loaded", "RunSpec", "load_and_prepare"]

#: Log bytes, all runs together, from which the runs are read in worker processes. Starting a
#: worker costs little (a fork), but below this the runs take about a second in all.
PARALLEL_BYTES = 16 * 2**20

#: A run to read: its log, its label, the payload fixed to the robot during it.
RunSpec = tuple[Path, str, Payload | None]


@dataclass(frozen=True)
class Loaded:
    """One run read and prepared, with what the report says of it."""

    prepared: PreparedRun
    info: RunInfo
    meta: dict[str, str]


class _Steps:
    """What reading a run tells its display: a description and a total, then advances."""

    def __init__(self, describe: Callable[[str, int | None], None], advance: Callable[[int], None]):
        self.describe = describe
        self.advance = advance


def load_and_prepare(
    model: RobotModel,
    specs: Sequence[RunSpec],
    req: IdentifyRequest,
    progress: Progress,
) -> tuple[dict[WristFriction, Any], list[Loaded]]:
    """Read and prepare every run of ``specs``, in the order given.

    Returns
    -------
    bases, loaded
        The base parameters of each friction form, and each run's prepared data.

    Raises
    ------
    InputError
        A log or an option is bad (from whichever run failed first in ``specs``' order).
    IdentificationError
        A worker process died without an answer.
    """
    bases = bases_for_forms(model)
    links = [pay.link for _, _, pay in specs if pay is not None]
    columns = stored_columns(model.robot, bases, links)
    workers = _worker_count(specs)
    if workers > 1:
        return bases, _in_workers(model, columns, specs, req, progress, workers)
    loaded = []
    for spec in specs:
        task = progress.add_task(f"reading {spec[1]} run", total=None)
        steps = _Steps(
            functools.partial(_describe, progress, task), functools.partial(progress.advance, task)
        )
        # one run at a time: a run's raw samples are dropped before the next is read
        loaded.append(_load_one(model, columns, spec, req, steps))
        progress.remove_task(task)
    return bases, loaded


def _describe(progress: Progress, task: Any, text: str, total: int | None) -> None:
    progress.update(task, description=text, total=total)


def _worker_count(specs: Sequence[RunSpec]) -> int:
    """Worker processes to use: 1 (none) for short logs or where a fork is not safe."""
    if len(specs) < 2 or not fork_is_safe():
        return 1
    try:
        size = sum(path.stat().st_size for path, _, _ in specs)
    except OSError:
        return 1  # the sequential path names the missing file
    if size < PARALLEL_BYTES:
        return 1
    return min(len(specs), len(os.sched_getaffinity(0)))


def _load_one(
    model: RobotModel, columns: Sequence[str], spec: RunSpec, req: IdentifyRequest, steps: _Steps
) -> Loaded:
    path, label, payload = spec
    run = load_run(path, model.robot, label, payload, req.current)
    steps.describe(f"{label}: filters, regressor, decimation", run.q.shape[0])
    asked = _filter_for(run, req)
    prepared = prepare_recording(
        model,
        columns,
        label=run.label,
        q=run.q,
        current=run.current,
        rate_hz=run.rate_hz,
        settings=asked,
        payload=run.payload,
        source=str(run.path),
        t0=run.t0,
        progress=steps.advance,
        period_s=trajectory_period(run.attachments),
    )
    prepared = dataclasses.replace(prepared, phase_origin_s=run.excitation_start_s)
    return Loaded(prepared, _run_info(run, prepared, asked), dict(run.meta))


def _filter_for(run: LoadedRun, req: IdentifyRequest) -> FilterSettings:
    bandwidth = trajectory_bandwidth(run.attachments)
    try:
        settings = default_filter(
            run.rate_hz,
            bandwidth,
            cutoff_hz=req.cutoff,
            decimate=req.decimate,
            current_delay=req.current_delay,
            sign_cutoff_hz=req.sign_cutoff,
            reversal_mask_s=req.reversal_mask,
            reversal_mask_drives=req.reversal_mask_drives,
        )
    except InputError as exc:
        raise InputError(f"run {run.label} ({run.path}): {exc}") from None
    if req.sign_at_cutoff:
        # the second candidate of the sign's choice (signchoice): the sign at the position's
        return at_position_cutoff(settings) or settings
    return settings


def _run_info(run: LoadedRun, prepared: PreparedRun, asked: FilterSettings) -> RunInfo:
    st = prepared.filter
    notes = list(run.notes)
    if prepared.rest_samples:
        notes.append(
            f"{prepared.rest_samples} samples with the robot at rest left out (and the "
            "decimated samples whose filter window reaches them)"
        )
    if st is not None and st.sign_cutoff < asked.sign_cutoff:
        notes.append(
            f"Coulomb sign's velocity filtered at {st.sign_cutoff:g} Hz, not "
            f"{asked.sign_cutoff:g} Hz: the encoder's step is coarse for these speeds "
            "(give --sign-cutoff to choose)"
        )
    return RunInfo(
        label=run.label,
        source=str(run.path),
        raw_samples=prepared.raw_samples,
        samples=prepared.samples,
        rate_hz=run.rate_hz,
        decimated_rate_hz=prepared.rate_hz,
        payload=run.payload.name if run.payload is not None else "none",
        time_base=None if run.time_base is None else run.time_base.as_dict(),
        current=run.channel,
        filter=None
        if st is None
        else {
            "cutoff_hz": st.cutoff_hz,
            "order": st.order,
            "decimate": st.decimate,
            "trim": st.trim,
            "current_delay": st.current_delay,
            "sign_cutoff_hz": st.sign_cutoff,
            "sign_noise_limit": st.sign_noise_limit,
            "reversal_mask_s": st.reversal_mask_s,
            # drive numbers from 1 whose coupled groups the mask weighs; null: every group
            "reversal_mask_drives": None
            if st.reversal_mask_drives is None
            else [d + 1 for d in st.reversal_mask_drives],
        },
        notes=notes,
    )


# --------------------------------------------------------------------------------------------
# Worker processes
#
# Messages from a worker, in order: ("describe", text, total) and ("advance", k) any number of
# times, then either ("done", Loaded without its regressor's series, their shape) followed by
# the series' raw bytes, or ("error", exception).


def _worker(
    conn: Connection, model: RobotModel, columns: Sequence[str], spec: RunSpec, req: IdentifyRequest
) -> None:
    """A worker process's whole life: one run read, prepared and sent back."""
    try:
        steps = _Steps(
            lambda text, total: conn.send(("describe", text, total)),
            lambda k: conn.send(("advance", k)),
        )
        with limited_blas_threads(1):  # the workers share the CPUs already
            loaded = _load_one(model, columns, spec, req, steps)
        reg = loaded.prepared.regressor
        series = np.ascontiguousarray(reg.series)
        light = dataclasses.replace(
            loaded,
            prepared=dataclasses.replace(
                loaded.prepared, regressor=dataclasses.replace(reg, series=np.empty(0))
            ),
        )
        conn.send(("done", light, series.shape))
        _write_raw(conn, series)
    except BaseException as exc:
        send_error(conn, exc)
    finally:
        conn.close()


def _write_raw(conn: Connection, array: np.ndarray) -> None:
    """Write ``array``'s bytes to the pipe unframed, right after the message announcing them.

    ``Connection.send_bytes``/``recv_bytes_into`` would do, but the receiving side assembles
    the whole message in a buffer of its own before copying it: a long run's series (about
    a hundred MB at 1 kHz for 10 minutes) would be held twice.
    """
    view = array.data.cast("B")
    fd = conn.fileno()
    while view:
        view = view[os.write(fd, view) :]


def _read_raw(conn: Connection, array: np.ndarray) -> None:
    """Fill ``array`` (C-contiguous) with the bytes :func:`_write_raw` sent, read in place.

    Raises
    ------
    EOFError
        The pipe ended first (the worker died while sending).
    """
    view = array.data.cast("B")
    fd = conn.fileno()
    while view:
        got = os.readv(fd, [view])
        if got == 0:
            raise EOFError("pipe closed")
        view = view[got:]


def _in_workers(
    model: RobotModel,
    columns: Sequence[str],
    specs: Sequence[RunSpec],
    req: IdentifyRequest,
    progress: Progress,
    workers: int,
) -> list[Loaded]:
    ctx = multiprocessing.get_context("fork")
    procs: list[Any] = []
    conns: dict[Connection, int] = {}
    tasks: dict[int, Any] = {}  # run -> its progress task
    results: list[Loaded | None] = [None] * len(specs)
    errors: dict[int, BaseException] = {}
    pending = list(range(len(specs)))
    try:
        while pending or conns:
            while pending and len(conns) < workers:
                i = pending.pop(0)
                ours, theirs = ctx.Pipe(duplex=False)
                proc = ctx.Process(
                    target=_worker,
                    args=(theirs, model, columns, specs[i], req),
                    name=f"drivegain-read-{specs[i][1]}",
                    daemon=True,
                )
                proc.start()
                theirs.close()
                procs.append(proc)
                conns[ours] = i
                tasks[i] = progress.add_task(f"reading {specs[i][1]} run", total=None)
            for conn in wait(list(conns)):
                assert isinstance(conn, Connection)
                if conn not in conns:  # dropped this round by an earlier run's failure
                    continue
                i = conns[conn]
                if _receive(conn, i, specs[i], progress, tasks[i], results, errors):
                    del conns[conn]
                    conn.close()
                    progress.remove_task(tasks[i])
                    if i in errors:  # the runs after it no longer matter: only the first
                        pending = [j for j in pending if j < i]  # failure is reported
                        for later in [c for c, j in conns.items() if j > i]:
                            progress.remove_task(tasks[conns.pop(later)])
                            later.close()
        for i in range(len(specs)):  # the first failure in the order of the runs
            if i in errors:
                raise errors[i]
        return [r for r in results if r is not None]
    finally:
        for conn in conns:
            conn.close()
        for proc in procs:
            if proc.is_alive():
                # SIGKILL: a worker has nothing to clean up, and SIGTERM may meet a handler the
                # parent had installed (it does not end a worker blocked writing to a pipe whose
                # reading end a sibling inherited).
                proc.kill()
            proc.join()


def _receive(
    conn: Connection,
    i: int,
    spec: RunSpec,
    progress: Progress,
    task: Any,
    results: list[Loaded | None],
    errors: dict[int, BaseException],
) -> bool:
    """Handle one message of worker ``i``; True when it has nothing more to say."""
    try:
        message = conn.recv()
    except EOFError:
        errors[i] = IdentificationError(
            f"run {spec[1]} ({spec[0]}): the process reading it ended without an answer"
        )
        return True
    kind = message[0]
    if kind == "describe":
        progress.update(task, description=message[1], total=message[2])
        return False
    if kind == "advance":
        progress.advance(task, message[1])
        return False
    if kind == "error":
        errors[i] = message[1]
        return True
    light, shape = message[1], message[2]
    series = np.empty(shape)
    try:
        _read_raw(conn, series)
    except EOFError:
        errors[i] = IdentificationError(
            f"run {spec[1]} ({spec[0]}): the process reading it ended while sending its data"
        )
        return True
    reg = dataclasses.replace(light.prepared.regressor, series=series)
    prepared = dataclasses.replace(light.prepared, regressor=reg)
    results[i] = dataclasses.replace(light, prepared=prepared)
    return True


def trajectory_bandwidth(attachments: Mapping[str, bytes]) -> float | None:
    """Highest harmonic (Hz) of the excitation trajectory attached to a log, if any."""
    fourier = attached_fourier(attachments)
    return None if fourier is None else fourier.base_frequency_hz * fourier.harmonics


def trajectory_period(attachments: Mapping[str, bytes]) -> float | None:
    """Period (s) of the excitation trajectory attached to a log, if any."""
    fourier = attached_fourier(attachments)
    return None if fourier is None else fourier.period_s
