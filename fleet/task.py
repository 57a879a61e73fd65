"""One identification of a batch, as a Dask worker runs it.

:func:`run_task` is idempotent: its result file, ``OUT/tasks/CAMPAIGN/ROBOT_ID/result.json``,
is written last and atomically, after the identification's reports, so its presence with the
task's fingerprint means the task is done; a task run again (a re-run of the batch, or Dask
rescheduling it after its worker died between writing and reporting) returns that file.
A failed identification (bad input, ill-posed data) is recorded with status ``failed`` and is
tried again by the next run of the batch.
"""

from __future__ import annotations

import json
import os
import socket
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from drivegain.errors import DrivegainError
from drivegain.fleet import storage
from drivegain.fleet.campaign import Task, robot_location

RESULT = "result.json"
RESULT_VERSION = 1


@dataclass
class TaskResult:
    """What one task produced (``result.json``).

    Attributes
    ----------
    task
        The task (its fields as a dict).
    fingerprint
        :meth:`Task.fingerprint` of the task that produced it.
    status
        ``ok`` or ``failed``.
    error
        One line, when failed.
    seconds
        Wall time of the identification on the worker, s.
    cpu_seconds
        CPU time of the worker process meanwhile, s (below ``seconds``: the core was shared).
    worker
        The worker that ran it (address, or host:pid).
    report
        The identification's ``report.json`` (contracts §5), when ok.
    files
        Locations of the identification's report files.
    """

    task: dict[str, Any]
    fingerprint: str
    status: str
    error: str | None = None
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    worker: str = ""
    report: dict[str, Any] | None = None
    files: list[str] = field(default_factory=list)
    format_version: int = RESULT_VERSION

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def to_json(self) -> bytes:
        return (json.dumps(asdict(self), indent=1) + "\n").encode()

    @classmethod
    def from_json(cls, data: bytes, location: str) -> TaskResult:
        """Parse a ``result.json``.

        Raises
        ------
        DataError
            Not a result file of this format.
        """
        from drivegain.errors import DataError

        try:
            doc = json.loads(data)
            doc.pop("format_version", None)
            return cls(**doc)
        except (ValueError, TypeError) as exc:
            raise DataError(f"not a batch result file ({exc})", file=location) from None


def task_folder(out: str, task: Task) -> str:
    """The results folder of ``task`` below the batch's ``out``."""
    return storage.join(out, "tasks", task.campaign, task.robot_id)


def done(out: str, task: Task) -> TaskResult | None:
    """The finished result of ``task`` if it is in ``out`` (same fingerprint, status ok)."""
    location = storage.join(task_folder(out, task), RESULT)
    try:
        result = TaskResult.from_json(storage.read_bytes(location), location)
    except DrivegainError:
        return None
    if result.ok and result.fingerprint == task.fingerprint():
        return result
    return None


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return f"{socket.gethostname()}:{os.getpid()}"


_PLOTS_LOCK = threading.Lock()
_plots_off = 0  # tasks running with plots off in this process
_write_plots: Any = None  # identification's own write_plots while it is switched off


def _no_plots(*args: Any, **kwargs: Any) -> dict[str, str]:
    return {}


@contextmanager
def _identify_plots(enabled: bool) -> Iterator[None]:
    """Let identification write its PNG plots, or not (``identify_plots = false``: most of an
    identification's time on short runs is matplotlib's). The switch is process-wide and
    counted, so thread workers running several such tasks at once restore it only when the
    last one ends; every task of a batch has the same setting."""
    global _plots_off, _write_plots
    if enabled:
        yield
        return
    from drivegain.identify import plots

    with _PLOTS_LOCK:
        if _plots_off == 0:
            _write_plots = plots.write_plots
            setattr(plots, "write_plots", _no_plots)  # noqa: B010
        _plots_off += 1
    try:
        yield
    finally:
        with _PLOTS_LOCK:
            _plots_off -= 1
            if _plots_off == 0:
                setattr(plots, "write_plots", _write_plots)  # noqa: B010


def _identify(task: Task, tmp: Path) -> dict[str, Any]:
    from drivegain.identify.pipeline import IdentifyRequest, run_identify

    def local(location: str | None) -> Path | None:
        return None if location is None else storage.local_copy(location, tmp)

    robot = local(robot_location(task.robot))
    gains = task.gains
    if gains is not None and gains not in ("apriori", "gear-ratios"):
        gains = str(local(gains))
    assert robot is not None
    req = IdentifyRequest(
        robot=robot,
        unloaded=storage.local_copy(task.unloaded, tmp),
        loaded=local(task.loaded),
        payload=local(task.payload),
        gains=gains,
        out=tmp / "report",
        progress=False,
    )
    with _identify_plots(task.identify_plots):
        outcome = run_identify(req)
    return outcome.report


def run_task(task: Task, out: str) -> TaskResult:
    """Identify one task and store its result below ``out`` (skipped when already done).

    Never raises for a failed identification (the result says why); raises only when the
    results cannot be written, which Dask retries.
    """
    previous = done(out, task)
    if previous is not None:
        return previous
    folder = task_folder(out, task)
    # A worker that died writing this task's files left its temporary ones: this run replaces
    # them (Dask runs a task again only once its first worker is gone).
    storage.remove_stale_parts(folder)
    start, cpu = time.perf_counter(), time.process_time()
    result = TaskResult(
        task=asdict(task), fingerprint=task.fingerprint(), status="ok", worker=_worker_name()
    )
    with tempfile.TemporaryDirectory(prefix="drivegain-batch-") as name:
        tmp = Path(name)
        try:
            result.report = _identify(task, tmp)
        except DrivegainError as exc:
            result.status, result.error = "failed", f"{type(exc).__name__}: {exc}"
        result.seconds = time.perf_counter() - start
        result.cpu_seconds = time.process_time() - cpu
        report_dir = tmp / "report"
        if result.ok and report_dir.is_dir():
            for f in sorted(report_dir.iterdir()):
                target = storage.join(folder, "report", f.name)
                storage.put_file(f, target)
                result.files.append(target)
    storage.write_atomic(storage.join(folder, RESULT), result.to_json())
    return result
