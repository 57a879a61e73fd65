"""A lockstep acquisition through the product's own code on the kernel's vcan0.

``drivegain acquire`` in a subprocess, as a user runs it, with ``[bus] interface = "socketcan"``,
``channel = "vcan0"`` and a ``[simulation]`` table: the simulated TX-40 drives and the master
each open their own socketcan socket on vcan0. The same run on python-can's ``virtual`` bus must
give the same cycles and setpoints (timing is not asserted: emulation is slow and noisy).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivegain.config import load_robot, resource_path
from drivegain.errors import DrivegainError
from drivegain.formats.fourier import FourierTrajectory
from drivegain.formats.logreader import RunLog, read_run
from drivegain.formats.trajectory import save_trajectory, trajectory_document

#: Bound of one acquisition subprocess under emulation, s.
ACQUIRE_TIMEOUT_S = 900


def write_trajectory(path: Path) -> Path:
    """About 3 s of motion: approach, one 2 s period of a small 0.5 Hz excitation, retreat."""
    robot = load_robot(resource_path("tx40.toml"))
    rng = np.random.default_rng(0)
    a = rng.uniform(-0.3, 0.3, (robot.n, 2))
    b = rng.uniform(-0.3, 0.3, (robot.n, 2))
    q0 = np.array([0.1, -0.2, 0.3, 0.0, 0.4, 0.0])
    f = FourierTrajectory(0.5, q0, a, b, 1)
    return save_trajectory(path, trajectory_document(f, robot, {"cond": 0.0}))


def write_config(path: Path, interface: str, channel: str, extra: str = "") -> Path:
    """The simulated TX-40 in lockstep on the given bus (the layout of acquire-sim.toml), with
    ``extra`` TOML lines at the end (injected faults)."""
    path.write_text(
        "\n".join(
            [
                "[acquisition]",
                f'robot = "{resource_path("tx40.toml")}"',
                "period_s = 0.004",
                "[bus]",
                f'interface = "{interface}"',
                f'channel = "{channel}"',
                "bitrate = 1000000",
                "[simulation]",
                'clock = "lockstep"',
                "seed = 3",
                "current_noise_nm = 0.05",
                "history_s = 5.0",
                extra,
            ]
        )
        + "\n"
    )
    return path


@dataclass
class Run:
    status: int
    output: str
    seconds: float
    log: RunLog | None


def acquire(
    folder: Path, interface: str, channel: str, trajectory: Path, extra: tuple[str, ...] = ()
) -> Run:
    folder.mkdir()
    cfg = write_config(folder / "acquire.toml", interface, channel)
    out = folder / "run.mcap"
    cmd = [sys.executable, "-m", "drivegain.cli", "acquire", "--config", str(cfg)]
    cmd += ["--trajectory", str(trajectory), "--out", str(out), *extra]
    t0 = time.monotonic()
    proc = subprocess.run(
        cmd, capture_output=True, text=True, timeout=ACQUIRE_TIMEOUT_S, cwd=folder
    )
    seconds = time.monotonic() - t0
    output = proc.stdout + proc.stderr
    log = None
    if out.exists():
        try:
            log = read_run(out)
        except DrivegainError as exc:  # reported by the tests, with the run's output
            output += f"\n(reading {out.name}: {exc})"
    return Run(proc.returncode, output, seconds, log)


@pytest.fixture(scope="module")
def trajectory(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_trajectory(tmp_path_factory.mktemp("traj") / "short.json")


@pytest.fixture(scope="module")
def runs(
    tmp_path_factory: pytest.TempPathFactory, trajectory: Path, candump: Callable[..., Any]
) -> dict[str, Run]:
    base = tmp_path_factory.mktemp("acquire-vcan")
    # candump beside the run, as a user watches the bus; the run records its own trace too
    with candump(["-L", "-r", str(4 << 20), "vcan0"], base / "candump.log", 30):
        time.sleep(2.0)  # let it open its socket (only frames after that are compared)
        trace = ("--can-trace", str(base / "vcan" / "trace.log"))
        got = {"vcan": acquire(base / "vcan", "socketcan", "vcan0", trajectory, trace)}
    if got["vcan"].status == 0:  # the reference is worth its minutes only then
        got["virtual"] = acquire(base / "virtual", "virtual", "vcan-test-reference", trajectory)
    return got


def test_lockstep_acquisition_over_vcan0_completes(runs: dict[str, Run]) -> None:
    run = runs["vcan"]
    print(f"socketcan/vcan0 run: {run.seconds:.1f} s wall\n{run.output}")
    assert run.status == 0, run.output
    assert run.log is not None and not run.log.truncated
    assert run.log.missing_cycles() == 0
    assert run.log.cycle.size > 500
    assert np.all(np.isfinite(run.log.position))


def test_vcan0_run_matches_the_virtual_bus_run(runs: dict[str, Run]) -> None:
    vcan = runs["vcan"]
    assert vcan.status == 0, "the vcan0 run failed (see the test above)"
    virtual = runs["virtual"]
    print(f"virtual run: {virtual.seconds:.1f} s wall")
    assert virtual.status == 0, virtual.output
    assert vcan.log is not None and virtual.log is not None
    assert vcan.log.cycle.size == virtual.log.cycle.size
    np.testing.assert_array_equal(vcan.log.cycle, virtual.log.cycle)
    np.testing.assert_array_equal(vcan.log.setpoint, virtual.log.setpoint)


def test_the_runs_trace_is_what_candump_saw_beside_it(
    runs: dict[str, Run], tmp_path_factory: pytest.TempPathFactory
) -> None:
    """The trace of ``--can-trace`` (python-can's logger on its own socket) opens with
    :class:`can.LogReader`, is named in the log, and holds exactly the frames ``candump -L``
    recorded over the same stretch of the bus: boot, configuration, every cycle, shutdown."""
    import can

    run = runs["vcan"]
    assert run.status == 0, run.output
    assert run.log is not None and run.log.meta["can_trace"] == "trace.log"
    folder = run.log.path.parent
    with can.LogReader(str(folder / "trace.log")) as reader:
        traced = [(m.arbitration_id, bytes(m.data)) for m in reader]
    with can.LogReader(str(folder.parent / "candump.log")) as reader:
        dumped = [(m.arbitration_id, bytes(m.data)) for m in reader]
    assert len(traced) > 3 * run.log.cycle.size  # SYNC, RPDOs and TPDOs of every cycle
    first = dumped.index(traced[0])
    window = dumped[first : first + len(traced)]
    # The same frames, none lost and none extra.
    assert Counter(window) == Counter(traced)
    # In the order each sender sent them. Frames of two senders sent at the same moment (an SDO
    # request from the master and the drive's answer) may reach two sockets in either order: on
    # an SMP kernel each CPU delivers the frames it queued, so only the order per CAN id is the
    # bus's own. (Seen in CI: candump had a drive's answer after the request, the trace before.)
    for can_id in sorted({i for i, _ in traced}):
        assert [f for f in window if f[0] == can_id] == [f for f in traced if f[0] == can_id]


def test_a_log_recorded_over_vcan0_is_identified(
    runs: dict[str, Run], tmp_path_factory: pytest.TempPathFactory
) -> None:
    """``drivegain identify`` reads the vcan0 log: the inverse dynamic model with the a priori
    gains fits the recorded currents (the dynamic parameters of the simulated TX-40)."""
    import json

    run = runs["vcan"]
    assert run.status == 0 and run.log is not None, run.output
    out = tmp_path_factory.mktemp("identify-vcan") / "report"
    cmd = [sys.executable, "-m", "drivegain.cli", "identify", "--robot", "tx40"]
    cmd += ["--unloaded", str(run.log.path), "--gains", "apriori", "--decimate", "2"]
    cmd += ["--out", str(out)]  # a 3 s run: little decimation, or the filter borders eat it
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=ACQUIRE_TIMEOUT_S)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["method"]["samples"] > 0
    assert 0.0 < report["residual"]["relative"] < 0.5


def _mean_speed_at_end(position: np.ndarray, period_s: float = 0.004, cycles: int = 20) -> float:
    """Largest joint speed (rad/s) of a line fit over the last cycles: ~0 for a robot at rest
    (the simulated current noise moves a held joint by a few mrad/s)."""
    t = np.arange(cycles) * period_s
    return float(np.max(np.abs(np.polyfit(t, position[-cycles:], 1)[0])))


def test_a_drive_fault_over_vcan0_stops_the_robot_and_finishes_the_log(
    tmp_path: Path, trajectory: Path
) -> None:
    """An EMCY injected on node 3 one simulated second in: exit 1 and the log finished, with the
    fault as its last event (the drives' quick stop itself is checked on the simulated truth by
    tests/acquire; a subprocess shows only its log)."""
    folder = tmp_path / "fault"
    folder.mkdir()
    fault = '[[simulation.fault]]\nkind = "emcy"\nnode = 3\nat_s = 1.0'
    cfg = write_config(folder / "acquire.toml", "socketcan", "vcan0", fault)
    out = folder / "run.mcap"
    cmd = [sys.executable, "-m", "drivegain.cli", "acquire", "--config", str(cfg)]
    cmd += ["--trajectory", str(trajectory), "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=ACQUIRE_TIMEOUT_S)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    log = read_run(out)
    assert not log.truncated
    last = log.events[-1]  # the fault is the last event, named by node and EMCY code
    assert last["node"] == 3 and last["level"] == "error" and "EMCY" in last["text"], last
    assert 0.9 < log.t[-1] < 1.5  # the log ends at the fault, long before the run's end


def test_sigterm_over_vcan0_brings_the_robot_to_rest(tmp_path: Path) -> None:
    """SIGTERM in the middle of a long run: jerk-limited stop, exit 0, a finished log."""
    folder = tmp_path / "sigterm"
    folder.mkdir()
    robot = load_robot(resource_path("tx40.toml"))
    rng = np.random.default_rng(0)
    a = rng.uniform(-0.3, 0.3, (robot.n, 2))
    b = rng.uniform(-0.3, 0.3, (robot.n, 2))
    q0 = np.array([0.1, -0.2, 0.3, 0.0, 0.4, 0.0])
    long = save_trajectory(
        folder / "long.json",
        trajectory_document(FourierTrajectory(0.5, q0, a, b, 40), robot, {"cond": 0.0}),
    )
    cfg = write_config(folder / "acquire.toml", "socketcan", "vcan0")
    out = folder / "run.mcap"
    cmd = [sys.executable, "-m", "drivegain.cli", "acquire", "--config", str(cfg)]
    cmd += ["--trajectory", str(long), "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    part = out.with_name(out.name + ".part")
    deadline = time.monotonic() + ACQUIRE_TIMEOUT_S
    try:  # a few seconds of cycles flushed (the log is fsynced about every second)
        while not (part.exists() and part.stat().st_size > 200_000):
            assert proc.poll() is None, proc.communicate()[0]
            assert time.monotonic() < deadline, "no cycles recorded"
            time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        output, _ = proc.communicate(timeout=ACQUIRE_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, output
    log = read_run(out)
    assert not log.truncated and log.t[-1] < 80.0
    assert any("SIGTERM" in str(e.get("text", "")) for e in log.events), log.events[-5:]
    assert _mean_speed_at_end(log.position) < 0.05
