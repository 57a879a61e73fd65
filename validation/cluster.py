"""Where the study's Monte Carlo runs: here, on local worker processes, or on a Dask cluster.

:func:`run_monte_carlo` is the entry of :func:`~drivegain.validation.study.run_study` and of
``benchmarks/validate.py --scheduler tcp://HOST:PORT`` (issue 21): every (seed, scenario) pair is
one task, the results are the same wherever they run (every seed draws from its own stream).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

from drivegain.errors import InputError
from drivegain.validation.estimators import SeedResult, monte_carlo
from drivegain.validation.scenarios import SCENARIOS, Scenario
from drivegain.validation.world import World

#: Time allowed to connect to a Dask scheduler, s.
CONNECT_TIMEOUT_S = 30.0
#: Dask's loggers, quietened to WARNING while the study talks to the cluster.
_NOISY = ("distributed", "dask", "tornado", "bokeh")


def check_scheduler(address: str | None) -> None:
    """Refuse a scheduler address that is not ``tcp://HOST:PORT`` (or another Dask scheme).

    Raises
    ------
    InputError
        If ``address`` has no ``scheme://`` or no port.
    """
    if address is None:
        return
    scheme, sep, rest = address.partition("://")
    host, colon, port = rest.rpartition(":")
    if not sep or not scheme or not colon or not host or not port.isdigit():
        raise InputError(
            f"--scheduler must look like tcp://HOST:PORT, got {address!r}", key="scheduler"
        )


@contextmanager
def _dask_executor(address: str, world: World) -> Iterator[tuple[Executor, Any]]:
    """An executor on the Dask scheduler at ``address`` and ``world`` scattered to its workers.

    Raises
    ------
    InputError
        If the scheduler does not answer within :data:`CONNECT_TIMEOUT_S`.
    """
    from distributed import Client

    levels = {name: logging.getLogger(name).level for name in _NOISY}
    for name in _NOISY:
        logging.getLogger(name).setLevel(logging.WARNING)
    try:
        try:
            client = Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise InputError(
                f"cannot reach the Dask scheduler {address} ({exc})", key="scheduler"
            ) from None
        try:
            # Sent once to every worker, not once per task (about 1 MB with the Pinocchio model).
            ref = client.scatter(world, broadcast=True)
            yield client.get_executor(pure=False), ref
        finally:
            client.close()
    finally:
        for name, level in levels.items():
            logging.getLogger(name).setLevel(level)


def run_monte_carlo(
    world: World,
    seeds: int,
    deadline: float,
    scenarios: Sequence[Scenario] = SCENARIOS,
    progress: Callable[[str], None] = print,
    *,
    scheduler: str | None = None,
    workers: int = 1,
) -> dict[str, list[SeedResult]]:
    """:func:`~drivegain.validation.estimators.monte_carlo` here, on processes or on Dask.

    Parameters
    ----------
    world, seeds, deadline, scenarios, progress
        As for :func:`~drivegain.validation.estimators.monte_carlo` (``deadline``: a
        :func:`time.perf_counter` value, s).
    scheduler
        Address of a running Dask scheduler (``tcp://HOST:PORT``): the seeds run on its
        workers, which need drivegain installed. ``None``: on this machine.
    workers
        Without ``scheduler``: local worker processes (1: in this process, one seed after the
        other).

    Raises
    ------
    InputError
        A malformed or unreachable scheduler address, or ``workers`` below 1.
    """
    check_scheduler(scheduler)
    if workers < 1:
        raise InputError("--workers must be at least 1", key="workers")
    if scheduler is not None:
        with _dask_executor(scheduler, world) as (executor, ref):
            progress(f"Monte Carlo on the Dask scheduler {scheduler}")
            return monte_carlo(ref, seeds, deadline, scenarios, progress, executor)
    if workers == 1:
        return monte_carlo(world, seeds, deadline, scenarios, progress)
    with ProcessPoolExecutor(workers) as pool:
        return monte_carlo(world, seeds, deadline, scenarios, progress, pool)
