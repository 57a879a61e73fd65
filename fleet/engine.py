"""Running a batch's identifications on Dask: a local cluster, or an existing scheduler.

One Dask task per identification (:func:`drivegain.fleet.task.run_task`), submitted with
``retries`` (a task that raises is tried again) and not pure (a task is run, never taken from a
cache). A worker that dies mid-task loses nothing: the scheduler reschedules its tasks on the
other workers (up to Dask's ``distributed.scheduler.allowed-failures`` deaths per task), and a
task whose result file was already written returns it. Tasks already done (a result file with
the same fingerprint in the results folder) are not submitted at all: re-running a batch only
computes what is missing or failed.

With ``--scheduler``, the workers read the inputs and write the results themselves: every
location must mean the same to them (a shared folder, or object storage through its fsspec
backend installed on the workers), and drivegain must be installed there.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from typing import Any

from drivegain.errors import DrivegainError, InputError
from drivegain.fleet.campaign import Batch, Task
from drivegain.fleet.task import TaskResult, done, run_task

#: Loggers of Dask that talk at INFO on every start, stop and worker restart.
_NOISY = ("distributed", "dask", "tornado", "bokeh")


class SchedulerError(DrivegainError):
    """The Dask scheduler cannot be reached or the cluster cannot start."""


@dataclass(frozen=True)
class EngineOptions:
    """Where and how the tasks run.

    Attributes
    ----------
    scheduler
        Address of an existing Dask scheduler (``tcp://HOST:PORT``); ``None`` starts a
        ``LocalCluster`` on this machine for the batch.
    workers
        Workers of the local cluster (default: the machine's cores, at most the task count).
    processes
        Local workers as processes (default; identification draws its plots with pyplot, which
        is not thread-safe, so thread workers each run one task at a time anyway).
    progress
        Print one line per finished task on stderr.
    timeout_s
        Time allowed to connect to the scheduler, s.
    """

    scheduler: str | None = None
    workers: int | None = None
    processes: bool = True
    progress: bool = True
    timeout_s: float = 30.0


@dataclass
class BatchOutcome:
    """What :func:`run_batch` did."""

    results: list[TaskResult]
    computed: int
    skipped: int
    failed: int
    seconds: float
    workers: int
    errors: list[str] = field(default_factory=list)


#: Called with each task result as it arrives, and the Dask client (tests kill a worker here).
OnResult = Callable[[TaskResult, Any], None]


@contextmanager
def quiet_dask(debug: bool = False) -> Iterator[None]:
    """Dask's loggers at WARNING for the duration (INFO with ``debug``)."""
    import distributed  # noqa: F401  (sets its loggers' levels when first imported)

    saved = {name: logging.getLogger(name).level for name in _NOISY}
    for name in _NOISY:
        logging.getLogger(name).setLevel(logging.INFO if debug else logging.WARNING)
    try:
        yield
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


@contextmanager
def dask_client(engine: EngineOptions, tasks: int) -> Iterator[Any]:
    """A connected ``distributed.Client``: to ``engine.scheduler``, or to a new local cluster
    on 127.0.0.1 (no dashboard), closed on exit.

    Raises
    ------
    SchedulerError
        The scheduler does not answer within ``engine.timeout_s``.
    """
    from distributed import Client, LocalCluster

    if engine.scheduler is not None:
        try:
            client = Client(engine.scheduler, timeout=engine.timeout_s, set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise SchedulerError(
                f"cannot reach the Dask scheduler {engine.scheduler} ({exc})"
            ) from None
        try:
            yield client
        finally:
            client.close()
        return
    workers = engine.workers or max(1, min(tasks, os.cpu_count() or 1))
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=engine.processes,
        host="127.0.0.1",
        dashboard_address=None,
    )
    try:
        client = Client(cluster, set_as_default=False)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def _key(task: Task) -> str:
    return f"drivegain-identify-{task.campaign}-{task.robot_id}-{task.fingerprint()}"


def _line(i: int, total: int, r: TaskResult) -> str:
    t = r.task
    what = "ok" if r.ok else f"FAILED: {r.error}"
    return (
        f"batch: [{i}/{total}] {t['robot_id']} {t['campaign']}: {what} "
        f"({r.seconds:.1f} s on {r.worker})"
    )


def run_batch(
    batch: Batch,
    engine: EngineOptions | None = None,
    *,
    on_result: OnResult | None = None,
) -> BatchOutcome:
    """Identify every task of ``batch`` that is not done yet, on Dask.

    Parameters
    ----------
    batch
        Tasks and options (results folder, retries).
    engine
        Scheduler or local cluster (default: a local cluster).
    on_result
        Called in this process with each result as it arrives, and the client.

    Returns
    -------
    BatchOutcome
        Every task's result (computed now or found done), in the batch's order.

    Raises
    ------
    SchedulerError
        No scheduler, or the local cluster cannot start.
    InputError
        Two tasks with the same campaign and robot id.
    """
    engine = engine or EngineOptions()
    out = batch.options.out
    keys = [t.key for t in batch.tasks]
    if len(set(keys)) != len(keys):
        dup = sorted({k for k in keys if keys.count(k) > 1})
        raise InputError(f"robots listed twice in a campaign: {', '.join(dup)}", file=batch.source)
    start = time.perf_counter()
    results: dict[str, TaskResult] = {}
    pending = []
    for t in batch.tasks:
        previous = done(out, t)
        if previous is None:
            pending.append(t)
        else:
            results[t.key] = previous
    skipped = len(results)
    say = (lambda s: print(s, file=sys.stderr, flush=True)) if engine.progress else None
    if say is not None:
        say(f"batch: {len(batch.tasks)} identifications, {skipped} already done in {out}")
    errors: list[str] = []
    workers = 0
    if pending:
        from distributed import as_completed

        with dask_client(engine, len(pending)) as client:
            workers = len(client.scheduler_info().get("workers", {}))
            if say is not None:
                say(f"batch: {len(pending)} to run on {workers} Dask worker(s)")
            futures = {
                client.submit(
                    run_task, t, out, key=_key(t), retries=batch.options.retries, pure=False
                ): t
                for t in pending
            }
            for i, fut in enumerate(as_completed(futures, loop=client.loop), start=1):
                t = futures[fut]
                if fut.status == "error":
                    exc = fut.exception()
                    msg = f"{t.robot_id} {t.campaign}: {type(exc).__name__}: {exc}"
                    errors.append(msg)
                    r = TaskResult(
                        task=asdict(t), fingerprint=t.fingerprint(), status="failed", error=msg
                    )
                else:
                    r = fut.result()
                results[t.key] = r
                if say is not None:
                    say(_line(skipped + i, len(batch.tasks), r))
                if on_result is not None:
                    on_result(r, client)
    ordered = [results[t.key] for t in batch.tasks]
    return BatchOutcome(
        results=ordered,
        computed=len(pending),
        skipped=skipped,
        failed=sum(not r.ok for r in ordered),
        seconds=time.perf_counter() - start,
        workers=workers,
        errors=errors,
    )
