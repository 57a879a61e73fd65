"""One session in the foreground: bring the cell up, run on a cycle thread, show progress.

The cycle loop gets its own thread; the calling (main) thread receives the signals, draws the
progress display and waits. Nothing is written before every check has passed.
"""

from __future__ import annotations

import logging
import sys
import threading
from contextlib import nullcontext
from typing import Any

from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from drivegain.acquire.config import AcquisitionConfig
from drivegain.acquire.recorder import discard_unrecorded, unwritable_log
from drivegain.acquire.request import PreparedRun, RunRequest, prepare_run_interruptible
from drivegain.acquire.rig import Rig, simulation_for_run
from drivegain.acquire.session import RunResult, RunState, Session
from drivegain.acquire.stop import StopRequest
from drivegain.console import console as shared_console
from drivegain.drivers.sim import SimConfig
from drivegain.errors import OperatorStop

log = logging.getLogger(__name__)


def run_foreground(
    cfg: AcquisitionConfig,
    request: RunRequest,
    *,
    stop: StopRequest | None = None,
    progress: bool | None = None,
    simulation: SimConfig | None = None,
    seed: int | None = None,
    title: str | None = None,
) -> RunResult:
    """Check, boot, run one session and tear down.

    Parameters
    ----------
    cfg
        Acquisition configuration.
    request
        Trajectory, output log, label, payload.
    stop
        Operator stop requests (the caller installs the signal handlers).
    progress
        Draw a progress bar (default: when stderr is a terminal).
    simulation
        Simulation settings overriding the config's (else :func:`simulation_for_run`).
    seed
        Seed of the simulated noise for this run (simulation only).
    title
        Label of the progress bar.

    Returns
    -------
    RunResult
        FINISHED or STOPPED.

    Raises
    ------
    InputError
        Bad files or a bus that cannot carry the cycle (nothing written).
    OperatorStop
        A stop arrived before the motion started (nothing written).
    DriveError, RecorderError, TrajectoryError
        Faults; when the run had started the log is finished with the fault as the last event.
    """
    stop = stop if stop is not None else StopRequest()
    # on a worker: a signal during the checks is honoured at once (they are abandoned)
    prepared = prepare_run_interruptible(cfg, request, stop)
    sim = simulation
    if sim is None and cfg.simulation is not None:
        sim = simulation_for_run(cfg.simulation, request.payload, seed)
    # the rig records the trace: configuration and shutdown frames are in it too
    rig = Rig(cfg, simulation=sim, trace=prepared.request.can_trace)
    with rig as master:
        if stop.requested:
            raise OperatorStop(f"stopped by {stop.reason} before the drives were enabled")
        session = Session(
            cfg, master, prepared, stop=stop, pre_events=rig.boot_events, policy=rig.policy
        )
        session.plan()
        if stop.requested:
            raise OperatorStop(f"stopped by {stop.reason} before the drives were enabled")
        try:
            return _run_on_thread(session, prepared, progress, title)
        except BaseException:
            # a log that could not even be started would block the retry; one with cycles stays
            discard_unrecorded(request.out)
            raise


def _run_on_thread(
    session: Session, prepared: PreparedRun, progress: bool | None, title: str | None
) -> RunResult:
    outcome: dict[str, Any] = {}

    def target() -> None:
        outcome.update(run_session(session))

    thread = threading.Thread(target=target, name="drivegain-cycle")
    show = sys.stderr.isatty() if progress is None else progress
    label = title or prepared.label
    bar = (
        Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            TextColumn("{task.fields[phase]:<10} t={task.completed:7.2f}/{task.total:.2f} s"),
            TimeElapsedColumn(),
            console=shared_console(stderr=True),  # log lines go above the live bar
            transient=False,
        )
        if show
        else None
    )
    with bar if bar is not None else nullcontext():
        task = (
            bar.add_task(label, total=max(session.duration_s, 1e-9), phase="enabling")
            if bar is not None
            else None
        )
        thread.start()
        last_state = None
        while thread.is_alive():
            thread.join(timeout=0.1)
            if session.state != last_state:
                last_state = session.state
                if bar is None:  # the bar shows the phase itself
                    log.info("%s: %s", label, session.state.value)
            if bar is not None and task is not None:
                bar.update(task, completed=session.t, phase=session.state.value)
        if bar is not None and task is not None:
            bar.update(task, completed=session.t, phase=session.state.value)
    if "error" in outcome:
        raise outcome["error"]
    result: RunResult = outcome["result"]
    return result


def run_session(session: Session) -> dict[str, Any]:
    """Run a session on the calling thread: ``{"result": RunResult}`` or ``{"error": exc}``.

    An ``OSError`` before the drives were enabled (the log could not be created: a full disk)
    becomes one line naming the file (:func:`~drivegain.acquire.recorder.unwritable_log`).
    """
    try:
        return {"result": session.run()}
    except OSError as exc:
        if session.state is RunState.PLANNED:
            return {"error": unwritable_log(exc, session.prepared.request.out)}
        return {"error": exc}
    except BaseException as exc:  # handed to the waiting thread, which raises it
        return {"error": exc}
