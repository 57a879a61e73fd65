"""Simulated drives in a child process on the ``drivegain-ipc`` bus, as realtime runs are timed.

These tests assert behaviour only: a run completes with every cycle in its log, the robot
follows its setpoints and comes to rest, signals and kills reach the right processes. Timing
(jitter, latencies, late cycles) is measured by ``benchmarks/bench_acquire.py``, never judged
here, since the machine that runs the suite is shared.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from pathlib import Path
from subprocess import Popen
from types import SimpleNamespace

import numpy as np
import pytest

from drivegain.acquire.config import load_acquisition_config
from drivegain.acquire.foreground import run_foreground
from drivegain.acquire.rig import Rig
from drivegain.acquire.session import RunRequest, RunState
from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.drivers.bus import BusConfig
from drivegain.drivers.clock import Clock
from drivegain.drivers.sim import SimConfig
from drivegain.drivers.simprocess import SimulatedCellProcess, drives_in_child_process
from drivegain.errors import BusError, ConfigError
from drivegain.formats.logreader import read_run

#: The realtime runs here check what a realtime run does, not how punctual the machine is: the
#: timing supervision is switched off (no number of late cycles stops a run, a TPDO is missing
#: only when the drives are gone, not late, and heartbeats may stay away for seconds, both the
#: drives' and the master's, whose threads a saturated machine holds up beyond the defaults of
#: 0.35 s and 0.3 s). A stalled shared machine is then slower, never a failure. The
#: supervision itself is tested on a fake clock (test_timing_and_supervision.py) and with
#: injected faults in lockstep (test_session.py).
NO_TIMING_FAULTS = {
    "tpdo_timeout_s": "5.0",
    "max_overruns": "1000000",
    "heartbeat_timeout_s": "5.0",
    "master_heartbeat_s": "2.0",
}
RELAXED = "\n".join(f"{k} = {v}" for k, v in NO_TIMING_FAULTS.items())


def _group_alive(pgid: int) -> list[int]:
    """Live (not zombie) processes of a process group."""
    alive = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            alive.append(int(entry))
    return alive


def _assert_group_ends(pgid: int, timeout: float = 10.0) -> None:
    """Every process of the group ends within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while _group_alive(pgid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _group_alive(pgid)


def _ipc_config(make_config: Callable[..., Path]) -> Path:
    """Drives in a child process, flushed often (for runs killed midway).

    Lockstep: the tests that use it are about processes and signals, which behave the same on
    either clock. Drives in another process cannot share the master's simulated clock, so the
    heartbeat consumers on both sides count wall time there: relaxed as in NO_TIMING_FAULTS, so
    that a busy machine cannot end the run before the signal does.
    """
    return make_config(
        clock="lockstep",
        interface="drivegain-ipc",
        acquisition="\n".join(
            ["flush_interval_s = 0.2", "master_heartbeat_s = 2.0", "heartbeat_timeout_s = 5.0"]
        ),
    )


def test_realtime_run_with_the_drives_in_a_child_process(
    tmp_path: Path,
    make_config: Callable[..., Path],
    short_trajectory: Path,
    acquire_cli: SimpleNamespace,
) -> None:
    path = make_config(clock="realtime", interface="drivegain-ipc", acquisition=RELAXED)
    cfg = load_acquisition_config(path)
    out = tmp_path / "run.mcap"
    res = run_foreground(cfg, RunRequest(short_trajectory, out), progress=False)
    assert res.state is RunState.FINISHED
    log = read_run(out)
    assert not log.truncated
    np.testing.assert_array_equal(log.cycle, np.arange(res.cycles))
    assert log.events[-1]["text"] == f"run finished: {res.cycles} cycles"
    # the drives in the other process moved the robot along the setpoints (one period behind
    # in cyclic synchronous position mode, ~1 rad/s: about 0.01 rad)
    assert np.abs(log.position - log.setpoint).max() < 0.03
    assert np.ptp(log.position, axis=0).max() > 0.3
    acquire_cli.assert_at_rest(log.position, log.sync_period_s)  # and it ends at rest
    assert not Path(cfg.bus.channel).exists()  # the child removed its socket


def _shipped_without_timing_faults(name: str, dest: Path) -> Path:
    """The shipped config ``name`` with its relative files made absolute and no timing faults."""
    overrides = NO_TIMING_FAULTS
    lines = resource_path(name).read_text().splitlines()
    assert lines.count("[acquisition]") == 1, f"{name}: expected one [acquisition] table"
    out = []
    for line in lines:
        key, _, value = (part.strip() for part in line.partition("="))
        if key in overrides:
            continue
        if key in ("robot", "truth"):
            relative = value.split("#", 1)[0].strip().strip('"')
            line = f'{key} = "{resource_path(relative)}"'
        out.append(line)
        if line == "[acquisition]":
            out += [f"{k} = {v}" for k, v in overrides.items()]
    dest.write_text("\n".join(out) + "\n")
    cfg = load_acquisition_config(dest)
    shipped = load_acquisition_config(resource_path(name))
    # the copy differs from the shipped config in its timing supervision only
    assert cfg.supervision.max_overruns == int(NO_TIMING_FAULTS["max_overruns"])
    assert cfg.tpdo_timeout_s == float(NO_TIMING_FAULTS["tpdo_timeout_s"])
    assert (cfg.robot_path, cfg.period_s, cfg.bus, cfg.rt_priority) == (
        shipped.robot_path,
        shipped.period_s,
        shipped.bus,
        shipped.rt_priority,
    )
    assert cfg.simulation == shipped.simulation
    return dest


def test_the_shipped_realtime_config_runs(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    short_trajectory: Path,
    acquire_cli: SimpleNamespace,
) -> None:
    monkeypatch.chdir(tmp_path)  # its bus socket is relative to the working directory
    config = _shipped_without_timing_faults("acquire-sim-realtime.toml", tmp_path / "rt.toml")
    args = ["acquire", "--config", str(config), "--trajectory", str(short_trajectory)]
    status = main([*args, "--out", "run.mcap"])
    assert status == 0
    log = read_run(tmp_path / "run.mcap")
    assert not log.truncated
    np.testing.assert_array_equal(log.cycle, np.arange(log.cycle.size))
    assert log.events[-1]["text"] == f"run finished: {log.cycle.size} cycles"
    acquire_cli.assert_at_rest(log.position, log.sync_period_s)
    assert not (tmp_path / "drivegain-sim-bus.sock").exists()
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the run's SCHED_FIFO is undone


def test_a_signal_to_the_process_group_still_stops_the_robot_safely(
    long_run: Callable[..., tuple[Popen[bytes], int, Path]],
    make_config: Callable[..., Path],
    acquire_cli: SimpleNamespace,
) -> None:
    """Ctrl-C or a service stop reaches the drives' process too: it keeps serving until the
    master has decelerated and disabled them."""
    cfg = _ipc_config(make_config)
    proc, _, out = long_run(cfg, 400, new_session=True)
    os.killpg(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err.decode()
    log = read_run(out)
    assert log.events[-1]["text"].startswith("operator stop (SIGTERM): robot at rest")
    acquire_cli.assert_at_rest(log.position, log.sync_period_s)
    _assert_group_ends(proc.pid)


def test_the_drives_process_ends_when_the_master_is_killed(
    long_run: Callable[..., tuple[Popen[bytes], int, Path]], make_config: Callable[..., Path]
) -> None:
    cfg = _ipc_config(make_config)
    proc, _, out = long_run(cfg, 200, new_session=True)
    assert len(_group_alive(proc.pid)) == 2  # the master and the drives
    proc.kill()
    proc.communicate(timeout=30)
    _assert_group_ends(proc.pid)
    assert read_run(out.with_name("run.mcap.part")).truncated


def test_killed_master_the_drives_stop_the_robot_on_their_own(
    long_run: Callable[..., tuple[Popen[bytes], int, Path]], make_config: Callable[..., Path]
) -> None:
    """SIGKILL of the master process mid-motion, the drives in their own process in realtime:
    nothing tells them but the silence of the master's heartbeat. Each drive's consumer (0x1016,
    three master periods: 6 s here) times out and its fault reaction ramps the robot to rest;
    the drives' process reports both on its standard error (shared with the master), then
    ends."""
    path = make_config(clock="realtime", interface="drivegain-ipc", acquisition=RELAXED)
    proc, _, _ = long_run(path, 400, new_session=True)
    assert len(_group_alive(proc.pid)) == 2  # the master and the drives
    proc.kill()
    # the drives' process holds the stderr pipe until it ends: generous bound, against a hang
    _, err = proc.communicate(timeout=120)
    text = err.decode()
    assert proc.returncode == -signal.SIGKILL
    timeouts = [line for line in text.splitlines() if "heartbeat consumer time-out" in line]
    assert len({line.split(":")[0] for line in timeouts}) == 6, text  # every drive noticed
    assert all("no heartbeat of node 127 for 6000 ms" in line for line in timeouts)
    assert "robot at rest after the master left (largest joint speed 0 rad/s" in text, text
    _assert_group_ends(proc.pid)


def test_a_child_that_cannot_start_is_a_clear_error(
    make_config: Callable[..., Path],
) -> None:
    cfg = load_acquisition_config(make_config(clock="realtime", interface="drivegain-ipc"))
    bad = type(cfg.bus)(cfg.bus.interface, "/nonexistent-dir/bus.sock", cfg.bus.bitrate)
    rig = Rig(type(cfg)(**{**cfg.__dict__, "bus": bad}))
    with pytest.raises(BusError, match=r"/nonexistent-dir/bus\.sock"):
        rig.open()
    assert rig.cell is None and rig.master is None


def test_the_process_host_needs_the_ipc_bus(make_config: Callable[..., Path]) -> None:
    cfg = load_acquisition_config(make_config())
    assert cfg.simulation is not None
    with pytest.raises(ConfigError, match="drivegain-ipc"):
        SimulatedCellProcess(cfg.robot, cfg.bus, cfg.simulation, cfg.period_s)
    # lockstep on a vcan device: the drives share the master's process (and simulated clock)
    vcan = BusConfig(interface="socketcan", channel="vcan0")
    with pytest.raises(ConfigError, match="lockstep shares its simulated clock"):
        SimulatedCellProcess(cfg.robot, vcan, cfg.simulation, cfg.period_s)


@pytest.mark.parametrize(
    ("interface", "clock", "child"),
    [
        ("virtual", "lockstep", False),
        ("virtual", "realtime", False),
        ("drivegain-ipc", "lockstep", True),
        ("drivegain-ipc", "realtime", True),
        ("socketcan", "lockstep", False),
        ("socketcan", "realtime", True),
    ],
)
def test_where_the_simulated_drives_run(interface: str, clock: str, child: bool) -> None:
    bus = BusConfig(interface=interface, channel="vcan0")
    assert drives_in_child_process(bus, SimConfig(clock=Clock(clock))) is child


def test_realtime_drives_on_socketcan_open_the_interface_in_their_own_process(
    tmp_path: Path,
) -> None:
    """A realtime simulation on socketcan: the rig starts the drives' process, which opens the
    configured interface itself. Where the device cannot be opened (this host's kernel has no
    CAN: tests/vcan runs the real thing) the child's own error reaches the caller, nothing is
    left open, and no drive was ever started in this process."""
    path = tmp_path / "acq.toml"
    path.write_text(
        f'[acquisition]\nrobot = "{resource_path("tx40.toml")}"\n'
        '[bus]\ninterface = "socketcan"\nchannel = "vcan97"\n'
        '[simulation]\nclock = "realtime"\n'
    )
    cfg = load_acquisition_config(path)
    started: list[SimulatedCellProcess] = []
    real_start = SimulatedCellProcess.start

    def start(self: SimulatedCellProcess) -> None:
        started.append(self)
        real_start(self)

    rig = Rig(cfg)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(SimulatedCellProcess, "start", start)
        with pytest.raises(BusError, match="vcan97"):
            rig.open()
    assert [c.bus_cfg for c in started] == [cfg.bus]  # the configured bus, unchanged
    assert started[0].pid is None and rig.cell is None and rig.master is None


def test_simulated_drives_never_go_on_a_real_bus(tmp_path: Path) -> None:
    path = tmp_path / "acq.toml"
    path.write_text(
        f'[acquisition]\nrobot = "{resource_path("tx40.toml")}"\n'
        '[bus]\ninterface = "socketcan"\nchannel = "can0"\n'
        "[simulation]\n"
    )
    with pytest.raises(ConfigError, match=r"interface.*never go on a real bus"):
        load_acquisition_config(path)
