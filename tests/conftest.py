"""Fixtures shared by all test folders."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def single_blas_thread() -> Iterator[None]:
    """One OpenBLAS thread for the session, as the identify command and the validation study
    run: its threads thrash on the shared, busy cores. Folders of numerical tests use it."""
    from drivegain.identify.blas import limited_blas_threads

    with limited_blas_threads(1):
        yield


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """``../shared`` beside the checkout (exists in CI, not in a user's clone)."""
    if not SHARED.is_dir():
        pytest.skip("../shared (real TX-40 data, docs) is not beside this checkout")
    return SHARED


@pytest.fixture(scope="session")
def tx40_real(shared_dir: Path) -> Path:
    d = shared_dir / "data" / "tx40-real"
    if not (d / "pos_read_data.csv").is_file():
        pytest.skip("../shared/data/tx40-real is missing")
    return d


# --- resource leak check (python-can style) ------------------------------------------------------
# A test that leaves a python-can bus open or a thread running (a CAN notifier, a simulator timer,
# a writer thread...) fails: the next test would otherwise inherit its traffic or its CPU.

_LEAK_GRACE_S = 2.0


def _virtual_bus_counts() -> dict[object, int]:
    import sys

    virtual = sys.modules.get("can.interfaces.virtual")
    if virtual is None:
        return {}
    with virtual.channels_lock:
        return {name: len(queues) for name, queues in virtual.channels.items()}


@pytest.fixture(autouse=True)
def _no_leaked_bus_or_thread():
    import sys
    import threading
    import time

    threads_before = set(threading.enumerate())
    buses_before = _virtual_bus_counts()
    freeze = sys.modules.get("drivegain.drivers.gcfreeze")
    holds_before = freeze.holders() if freeze is not None else 0
    yield
    deadline = time.monotonic() + _LEAK_GRACE_S
    while True:
        extra = [t for t in threading.enumerate() if t not in threads_before and t.is_alive()]
        buses = _virtual_bus_counts()
        grown = {
            name: n - buses_before.get(name, 0)
            for name, n in buses.items()
            if n > buses_before.get(name, 0)
        }
        if (not extra and not grown) or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    ipc = sys.modules.get("drivegain.drivers.ipcbus")
    if ipc is not None and len(ipc.OPEN_BUSES):
        problems_ipc = [str(b) for b in ipc.OPEN_BUSES]
    else:
        problems_ipc = []
    simproc = sys.modules.get("drivegain.drivers.simprocess")
    children = [c.pid for c in simproc.RUNNING] if simproc is not None else []
    freeze = sys.modules.get("drivegain.drivers.gcfreeze")
    holds = freeze.holders() - holds_before if freeze is not None else 0
    problems = []
    if holds:
        problems.append(f"{holds} garbage-collector freeze(s) left held (a master not closed)")
    if problems_ipc:
        problems.append(f"drivegain IPC bus(es) left open: {problems_ipc}")
    if children:
        problems.append(f"simulated cell process(es) left running: {children}")
    if grown:
        problems.append(f"python-can virtual bus(es) left open: {grown}")
    if extra:
        names = ", ".join(f"{t.name} (daemon={t.daemon})" for t in extra)
        problems.append(f"thread(s) left running: {names}")
    if problems:
        pytest.fail("resource leak: " + "; ".join(problems), pytrace=False)
