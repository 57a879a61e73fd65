"""Fixtures shared by all test folders."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
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


def exact_prepared(
    model: Any,
    truth: Any,
    columns: Sequence[str],
    t: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    *,
    label: str,
    payload: Any = None,
    friction: Any = None,
    period_s: float | None = None,
) -> Any:
    """A noise-free run along the exactly tracked ``q, qd, qdd`` (times ``t``, s): the true
    robot's currents (:func:`simulate_run`, wrist ``friction``), prepared with the exact
    derivatives (:func:`prepare_exact`, no filter)."""
    from drivegain.identify.prepare import prepare_exact
    from drivegain.identify.synth import simulate_run

    sim = simulate_run(model, truth, q, qd, qdd, payload=payload, friction=friction)
    return prepare_exact(
        model,
        columns,
        label=label,
        t=t,
        q=q,
        qd=qd,
        qdd=qdd,
        current=sim.current_reference,
        payload=payload,
        period_s=period_s,
    )


@pytest.fixture(scope="session")
def simulate_exact() -> Callable[..., Any]:
    """:func:`exact_prepared`, as
    ``simulate_exact(model, truth, columns, t, q, qd, qdd, label=..., payload=...)``."""
    return exact_prepared


def write_table_csv(path: Path, data: dict[str, np.ndarray]) -> Path:
    """The columns ``data`` (name → values) as a CSV table with a header row, at ``path``."""
    names = list(data)
    rows = np.column_stack([data[k] for k in names])
    lines = [",".join(names)] + [",".join(repr(float(v)) for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="session")
def table_csv() -> Callable[[Path, dict[str, np.ndarray]], Path]:
    """:func:`write_table_csv`: ``table_csv(path, {"time": t, "q1": ..., ...})``."""
    return write_table_csv


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
