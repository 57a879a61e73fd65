"""Realtime acquisitions on the kernel's vcan0, the simulated drives in a process of their own.

``drivegain acquire`` in a subprocess with ``[bus] interface = "socketcan"``, ``channel =
"vcan0"`` and a realtime ``[simulation]``: the rig starts the drives' process
(``python -m drivegain.drivers.simprocess``), which opens its own socketcan socket on vcan0 as
the master does; the kernel carries every frame between the two. The run's raw trace comes from
``[acquisition] can_trace`` in the TOML.

Timing is not asserted (emulation is slow and noisy): the timing supervision is relaxed as in
tests/acquire/test_simprocess.py, so a slow guest makes a run longer, never a failure.
Correctness is: states, a complete log, a robot at rest, the trace against the kernel's frame
counter, and kernel error frames reaching the supervision.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np
import pytest

from drivegain.config import load_robot, resource_path
from drivegain.errors import DrivegainError
from drivegain.excite.trajectory import load_trajectory
from drivegain.formats.logreader import RunLog, iter_channel, read_run
from drivegain.formats.trajectory import save_trajectory, trajectory_document

CHANNEL = "vcan0"
#: Bound of one acquisition subprocess under emulation, s.
ACQUIRE_TIMEOUT_S = 900
#: The timing supervision off, as in tests/acquire/test_simprocess.py (NO_TIMING_FAULTS): a TPDO
#: is missing only when the drives are gone, heartbeats may stay away for seconds, no number of
#: late cycles stops a run.
RELAXED = {
    "tpdo_timeout_s": "5.0",
    "max_overruns": "1000000",
    "heartbeat_timeout_s": "5.0",
    "master_heartbeat_s": "2.0",
}
#: socketcan error classes (linux/can/error.h): a bus error (tolerated, logged), bus-off (fatal).
CAN_ERR_BUSERROR = 0x80
CAN_ERR_BUSOFF = 0x40


def write_config(folder: Path, extra: str = "") -> Path:
    """The simulated TX-40 in realtime on vcan0 (the shipped acquire-sim-realtime.toml on the
    kernel device, timing supervision relaxed), a trace beside each log."""
    path = folder / "acquire.toml"
    lines = [
        "[acquisition]",
        f'robot = "{resource_path("tx40.toml")}"',
        "period_s = 0.004",
        "flush_interval_s = 0.2",
        'can_trace = "{log}.log"',
        *(f"{k} = {v}" for k, v in RELAXED.items()),
        extra,
        "[bus]",
        'interface = "socketcan"',
        f'channel = "{CHANNEL}"',
        "bitrate = 1000000",
        "[simulation]",
        'clock = "realtime"',
        "seed = 1",
        "current_noise_nm = 0.05",
        "history_s = 5.0",
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def vcan_counter(name: str) -> int:
    return int(Path(f"/sys/class/net/{CHANNEL}/statistics/{name}").read_text())


def drive_processes(parent: int) -> list[int]:
    """Children of ``parent`` that serve the simulated drives."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ")
        except (OSError, IndexError, ValueError):
            continue
        if ppid == parent and b"drivegain.drivers.simprocess" in cmdline:
            found.append(int(entry.name))
    return found


def cycles_in(part: Path) -> int:
    """Cycles flushed so far to a log being written (0 while a chunk is half written)."""
    if not part.exists():
        return 0
    try:
        return sum(1 for _ in iter_channel(part, "/joint_states"))
    except Exception:
        return 0


@dataclass
class Run:
    status: int
    output: str
    log: RunLog
    trace: list[can.Message]
    children: list[int]
    sent: int


def run_acquire(folder: Path, trajectory: Path, inject: list[tuple[int, list[str]]]) -> Run:
    """``drivegain acquire`` on vcan0; each ``(cycles, argv)`` of ``inject`` is run (a
    third-party sender on vcan0) once the log holds that many cycles."""
    cfg = write_config(folder)
    out = folder / "run.mcap"
    cmd = [sys.executable, "-m", "drivegain.cli", "acquire", "--config", str(cfg)]
    cmd += ["--trajectory", str(trajectory), "--out", str(out)]
    sent0 = vcan_counter("tx_packets")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    children: list[int] = []
    deadline = time.monotonic() + ACQUIRE_TIMEOUT_S
    try:
        pending = list(inject)
        while proc.poll() is None and (pending or not children):
            assert time.monotonic() < deadline, "the run did not get going"
            children = children or drive_processes(proc.pid)
            if pending and cycles_in(out.with_name("run.mcap.part")) >= pending[0][0]:
                subprocess.run(pending.pop(0)[1], check=True, timeout=60)
            time.sleep(0.2)
        output, _ = proc.communicate(timeout=ACQUIRE_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    sent = vcan_counter("tx_packets") - sent0
    assert out.exists(), output
    try:
        log = read_run(out)
    except DrivegainError as exc:  # an empty run: what the run printed says why
        raise AssertionError(f"{exc}\n{output}") from None
    with can.LogReader(str(folder / "run.log")) as reader:
        trace = list(reader)
    return Run(proc.returncode, output, log, trace, children, sent)


def shipped_excerpt(path: Path) -> Path:
    """One period (10 s) of the shipped TX-40 excitation (config/tx40-excitation.json)."""
    shipped = load_trajectory(resource_path("tx40-excitation.json"))
    robot = load_robot(resource_path("tx40.toml"))
    doc = trajectory_document(shipped.fourier.with_periods(1), robot, {"cond": 0.0})
    return save_trajectory(path, doc)


def mean_speed_at_end(position: np.ndarray, period_s: float, cycles: int = 20) -> float:
    """Largest joint speed (rad/s) of a line fit over the last cycles: ~0 at rest."""
    t = np.arange(cycles) * period_s
    return float(np.max(np.abs(np.polyfit(t, position[-cycles:], 1)[0])))


def final_speeds_rad_s(
    trace: list[can.Message], wire: tuple[list[int], np.ndarray, np.ndarray], period_s: float
) -> np.ndarray:
    """Each drive's speed, joint side, rad/s, between its last two reported positions (TPDO1
    bytes 0-3, motor encoder counts), read off the wire: what the drives said last. The TPDOs
    are at least a period apart, so dividing by the period can only overstate the speed."""
    node_ids, ratios, counts = wire
    speeds = []
    for j, node in enumerate(node_ids):
        pos = [
            int.from_bytes(bytes(m.data[:4]), "little", signed=True)
            for m in trace
            if m.arbitration_id == 0x180 + node and not m.is_error_frame
        ]
        assert len(pos) >= 2, f"node {node}: {len(pos)} TPDO1 frames in the trace"
        speeds.append(abs(pos[-1] - pos[-2]) / counts[j] * 2 * np.pi / ratios[j] / period_s)
    return np.array(speeds)


#: The master's wall-clock limit on an SDO answer (drivers/link.py Timeouts.sdo_s), s.
SDO_LIMIT_S = 0.5
#: Realtime runs here when the drives' process answers an SDO within this fraction of the limit.
PROBE_MARGIN = 0.2


#: Opt-in: in the QEMU/TCG guest on these (shared, loaded) machines the drives' process stops
#: answering once the drives are enabled (no SDO answer, no heartbeat for ~9 s: its realtime
#: physics cannot keep pace with the wall clock under emulation), measured on 2026-12-02 in two
#: guest runs. Set VCAN_REALTIME=1 where the machine keeps up (a real Linux host with vcan).
pytestmark = pytest.mark.skipif(
    os.environ.get("VCAN_REALTIME") != "1",
    reason="realtime drives on vcan0 need a machine that keeps wall-clock pace; under TCG "
    "emulation they stall after enabling (set VCAN_REALTIME=1 to run)",
)


@pytest.fixture(scope="module", autouse=True)
def keeps_up(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Skip this module where the machine cannot serve realtime drives: the master's SDO and
    state time-outs count wall time (0.5 s, 1 s) and are not relaxed by the configuration. A
    software-emulated guest on a busy host can be slower than that; then nothing here would
    test the code. Measured, not assumed: the drives' process is started on vcan0 as a run
    starts it, and 20 SDO reads of its node 1 (0.1 s apart) are timed."""
    import canopen
    from canopen.sdo.exceptions import SdoError

    from drivegain.acquire.config import load_acquisition_config
    from drivegain.drivers import objects as ob
    from drivegain.drivers.bus import open_network
    from drivegain.drivers.simprocess import SimulatedCellProcess

    cfg = load_acquisition_config(write_config(tmp_path_factory.mktemp("probe")))
    assert cfg.simulation is not None
    t0 = time.monotonic()
    cell = SimulatedCellProcess(cfg.robot, cfg.bus, cfg.simulation, cfg.period_s)
    rtt = [math.inf]
    try:
        cell.start()  # within SimulatedCellProcess's own start-up limit, or too slow
        started = time.monotonic() - t0
        network = open_network(cfg.bus)
        try:
            node = canopen.RemoteNode(cfg.robot.node_ids[0], str(ob.default_eds()))
            network.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = 30.0
            for _ in range(20):
                t = time.monotonic()
                node.sdo.upload(0x1000, 0)
                rtt.append(time.monotonic() - t)
                time.sleep(0.1)
            rtt.pop(0)
        finally:
            network.disconnect()
    except (DrivegainError, SdoError) as exc:  # no answer at all is too slow as well
        started = time.monotonic() - t0
        print(f"the drives' process did not serve: {exc}")
    finally:
        cell.stop()
    worst = max(rtt)
    print(f"drives' process: started in {started:.1f} s, SDO round trip max {worst:.3f} s")
    if worst > PROBE_MARGIN * SDO_LIMIT_S:
        pytest.skip(
            f"this machine is too slow for realtime drives: the drives' process on {CHANNEL} "
            f"answered an SDO in up to {worst:.2f} s (started in {started:.0f} s), the master "
            f"allows {SDO_LIMIT_S} s; the realtime vcan tests need answers within "
            f"{PROBE_MARGIN * SDO_LIMIT_S:.2f} s (a loaded host running the guest under TCG)"
        )


@pytest.fixture(scope="module")
def robot_wire() -> tuple[list[int], np.ndarray, np.ndarray]:
    robot = load_robot(resource_path("tx40.toml"))
    counts = np.array([j.encoder_counts for j in robot.joints], dtype=float)
    return list(robot.node_ids), np.abs(robot.gear_ratios), counts


def test_realtime_acquisition_over_vcan0_with_the_drives_in_their_own_process(
    tmp_path: Path, robot_wire: tuple[list[int], np.ndarray, np.ndarray]
) -> None:
    """One period of the shipped excitation in realtime: boot, enable, stream, retreat, disable;
    a complete MCAP log read back; the robot at rest at the end; the drives served from a child
    process; the configured trace holds every frame the kernel counted on vcan0."""
    trajectory = shipped_excerpt(tmp_path / "shipped-1-period.json")
    t0 = time.monotonic()
    run = run_acquire(tmp_path, trajectory, [])
    print(
        f"realtime vcan0 run: {time.monotonic() - t0:.1f} s wall, {run.sent} frames\n"
        f"{run.output[-3000:]}"
    )
    assert run.status == 0, run.output
    assert len(run.children) == 1, "the drives did not run in a process of their own"
    log = run.log
    assert log.meta["clock"] == "realtime" and log.meta["bus_interface"] == "socketcan"
    assert not log.truncated and log.missing_cycles() == 0
    np.testing.assert_array_equal(log.cycle, np.arange(log.cycle.size))
    texts = [str(e["text"]) for e in log.events]
    for expected in (
        "6 drives booted and operational",
        "drives enabled (OPERATION_ENABLED)",
        "phase approach",
        "phase excitation",
        "phase retreat",
        "drives disabled",
    ):
        assert expected in texts, (expected, texts)
    assert texts[-1] == f"run finished: {log.cycle.size} cycles"
    assert not [e for e in log.events if e["level"] == "error"]
    # the drives in the other process followed the setpoints and came to rest
    assert np.ptp(log.position, axis=0).max() > 0.3
    assert np.abs(log.position - log.setpoint).max() < 0.05
    assert mean_speed_at_end(log.position, log.sync_period_s) < 0.05
    # the trace: every frame vcan0 carried during the run, SYNCs and both sides' PDOs
    assert log.meta["can_trace"] == "run.log"
    assert len(run.trace) == run.sent, "the trace lost frames (or something else sent)"
    syncs = sum(1 for m in run.trace if m.arbitration_id == 0x80)
    tpdos = sum(1 for m in run.trace if m.arbitration_id == 0x181)
    assert syncs >= log.cycle.size and tpdos >= log.cycle.size
    assert np.all(final_speeds_rad_s(run.trace, robot_wire, log.sync_period_s) < 0.05)


def test_kernel_error_frames_reach_the_supervision(
    tmp_path: Path, robot_wire: tuple[list[int], np.ndarray, np.ndarray]
) -> None:
    """Error frames sent on vcan0 by third parties during a realtime run (the drives, the
    master and the senders are three processes; lockstep would miscount foreign frames):

    - a bus error (class 0x80, with can-utils' ``cansend``) is logged as a warning event and the
      run goes on (one error frame is tolerated; more than 10 per second would be a fault);
    - a bus-off (class 0x40, from a python-can socket) stops the run safely: exit 1, every
      drive quick-stopped and disabled, the log finished with the bus-off as its last event,
      the drives' last reported positions (read off the trace) at rest.
    """
    long = tmp_path / "long.json"
    shipped = load_trajectory(resource_path("tx40-excitation.json"))
    robot = load_robot(resource_path("tx40.toml"))
    save_trajectory(long, trajectory_document(shipped.fourier, robot, {"cond": 0.0}))
    bus_error = ["cansend", CHANNEL, f"{0x20000000 | CAN_ERR_BUSERROR:08X}#0000000000000000"]
    bus_off = [
        sys.executable,
        "-c",
        (
            "import can\n"
            f"with can.Bus(interface='socketcan', channel='{CHANNEL}') as bus:\n"
            f"    bus.send(can.Message(arbitration_id={CAN_ERR_BUSOFF}, is_error_frame=True,"
            " is_extended_id=False, data=bytes(8)))\n"
        ),
    ]
    run = run_acquire(tmp_path, long, [(300, bus_error), (600, bus_off)])
    print(run.output[-3000:])
    assert run.status == 1, run.output
    log = run.log
    assert not log.truncated and log.missing_cycles() == 0
    warned = [
        e for e in log.events if e["text"] == f"CAN error frame (class 0x{CAN_ERR_BUSERROR:X})"
    ]
    assert len(warned) == 1 and warned[0]["level"] == "warning", log.events[-10:]
    # the run went on streaming after the tolerated error frame...
    assert int(np.sum(log.log_time_ns > warned[0]["log_time_ns"])) > 100
    # ...and ended at the bus-off, the fault as the last event, long before the motion's end
    bus_offs = [e for e in log.events if e["text"] == "CAN bus-off"]
    assert len(bus_offs) == 1 and bus_offs[0]["level"] == "error"
    last = log.events[-1]
    assert last["level"] == "error" and "bus-off" in str(last["text"]), last
    assert last.get("action") == "quick stop"
    assert log.t[-1] < 30.0
    # both error frames are in the trace (python-can's trace formats keep that a frame was an
    # error frame, not its class: its candump-format writer stores every one as a bus error)
    assert sum(1 for m in run.trace if m.is_error_frame) == 2
    # every drive reported its quick stop, then standstill (QUICK_STOP_ACTIVE ends at rest),
    # while the master kept SYNC going; their last positions on the wire agree
    for node in robot_wire[0]:
        assert f"node {node}: CiA 402 QUICK_STOP_ACTIVE -> SWITCH_ON_DISABLED" in run.output
    assert np.all(final_speeds_rad_s(run.trace, robot_wire, log.sync_period_s) < 0.05)
