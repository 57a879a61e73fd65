"""Lockstep is deterministic whatever the machine is doing.

In lockstep every supervision time-out counts the simulated clock the master shares with the
simulated drives (drivers/simtime.py): a saturated machine makes a run slower, never different.
They run apart from the default suite (``make test-load``; CI runs it after ``make test``): they
keep every core busy for minutes. These tests saturate both cores with two busy processes they
start and stop themselves, and compare with the same run on the (otherwise) quiet machine: the
same cycles, bit for bit.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from drivegain.acquire.config import load_acquisition_config
from drivegain.acquire.demo import run_demo
from drivegain.acquire.foreground import run_foreground
from drivegain.acquire.session import RunRequest, RunState
from drivegain.config import load_robot, resource_path
from drivegain.excite.trajectory import save_trajectory, trajectory_document
from drivegain.formats.fourier import FourierTrajectory
from drivegain.formats.logreader import read_run

#: Busy processes: one per core of the machine the suite was measured on (2 cores).
BUSY = max(2, min(os.cpu_count() or 2, 4))


@contextmanager
def saturated() -> Iterator[None]:
    """Every core busy with a process that never sleeps, for the block."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(BUSY)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


def write_trajectory(path: Path, periods: int) -> Path:
    """A smooth 0.5 Hz excitation of the TX-40 (2 harmonics), well inside its limits (as the
    acquire tests' short trajectory, with a chosen number of periods)."""
    robot = load_robot(resource_path("tx40.toml"))
    rng = np.random.default_rng(0)
    a = rng.uniform(-0.3, 0.3, (robot.n, 2))
    b = rng.uniform(-0.3, 0.3, (robot.n, 2))
    q0 = np.array([0.1, -0.2, 0.3, 0.0, 0.4, 0.0])
    f = FourierTrajectory(0.5, q0, a, b, periods)
    return save_trajectory(path, trajectory_document(f, robot, {"cond": 0.0}))


def _run(config: Path, trajectory: Path, out: Path):
    cfg = load_acquisition_config(config)
    res = run_foreground(cfg, RunRequest(trajectory, out), progress=False)
    assert res.state is RunState.FINISHED, res
    log = read_run(out)
    assert not log.truncated
    np.testing.assert_array_equal(log.cycle, np.arange(res.cycles))
    return log


@pytest.mark.load
def test_a_60_s_lockstep_acquisition_is_the_same_on_a_saturated_machine(
    tmp_path: Path, make_config: Callable[..., Path]
) -> None:
    """A 60 s run beside two busy loops, against a 10 s run of the same excitation on the quiet
    machine: both finish, and every cycle they share (the approach and the first five periods,
    where their setpoints agree) is identical, positions and currents bit for bit."""
    config = make_config()
    quiet = _run(config, write_trajectory(tmp_path / "q.json", periods=5), tmp_path / "q.mcap")
    long = write_trajectory(tmp_path / "l.json", periods=30)  # 0.5 Hz: 60 s of excitation
    with saturated():
        loaded = _run(config, long, tmp_path / "l.mcap")
    assert loaded.t[-1] > 60.0
    differ = np.flatnonzero(np.any(quiet.setpoint != loaded.setpoint[: len(quiet.cycle)], axis=1))
    shared = int(differ[0]) if differ.size else len(quiet.cycle)
    assert shared > 0.8 * len(quiet.cycle)  # the retreat of the short run is all that differs
    for name in ("position", "current_reference", "current"):
        np.testing.assert_array_equal(getattr(loaded, name)[:shared], getattr(quiet, name)[:shared])


@pytest.mark.load
def test_the_demo_gives_the_same_gains_on_a_saturated_machine(tmp_path: Path) -> None:
    """The demo path (both runs over the mocked bus, then identification), on two periods of the
    shipped excitation to keep it short: the same identified gains, to the last bit."""
    doc = json.loads(resource_path("tx40-excitation.json").read_text())
    doc["periods"] = 2
    trajectory = tmp_path / "two-periods.json"
    trajectory.write_text(json.dumps(doc))
    quiet = run_demo(tmp_path / "quiet", trajectory=trajectory, progress=False)
    with saturated():
        loaded = run_demo(tmp_path / "loaded", trajectory=trajectory, progress=False)
    np.testing.assert_array_equal(loaded.identified, quiet.identified)
    np.testing.assert_array_equal(loaded.identified_std, quiet.identified_std)
    assert np.all(np.abs(loaded.relative_error) < 0.02)
