"""Sessions over the mocked CAN bus: complete logs, faults, operator stops, pre-motion checks."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from drivegain.acquire.config import load_acquisition_config
from drivegain.acquire.foreground import run_foreground
from drivegain.acquire.rig import Rig
from drivegain.acquire.session import (
    RunRequest,
    RunState,
    Session,
    prepare_run,
)
from drivegain.acquire.stop import StopRequest
from drivegain.acquire.supervision import SupervisionFault
from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.drivers.cia402 import State
from drivegain.errors import BusError, ConfigError, DataError, DriveError, InputError
from drivegain.excite.motion import Phase
from drivegain.excite.trajectory import load_trajectory, plan_excitation
from drivegain.formats.log import EventLevel
from drivegain.formats.logreader import read_run
from drivegain.identify.runs import excitation_start


def _messages(path: Path) -> dict[str, list[dict]]:
    """Every message of the log by topic, read with the mcap library's own reader."""
    out: dict[str, list[dict]] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.message_encoding != "json":
                continue  # the ROS 2 twin of /joint_states (CDR)
            out.setdefault(channel.topic, []).append(json.loads(message.data))
    return out


def test_run_logs_every_cycle_per_contract(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    cfg = load_acquisition_config(make_config())
    out = tmp_path / "run.mcap"
    payload = resource_path("payloads/calibrated-4590g.toml")
    res = run_foreground(cfg, RunRequest(short_trajectory, out, payload=payload), progress=False)
    assert res.state is RunState.FINISHED and res.path == out
    assert not out.with_name("run.mcap.part").exists()

    msgs = _messages(out)
    cycles = [m["cycle"] for m in msgs["/joint_states"]]
    assert cycles == list(range(res.cycles))  # every SYNC once, no gap
    assert [m["cycle"] for m in msgs["/drives/raw"]] == cycles
    ts = np.array([m["t"] for m in msgs["/joint_states"]])
    np.testing.assert_allclose(ts, np.arange(res.cycles) * 0.004, atol=1e-12)

    with open(out, "rb") as fh:
        reader = make_reader(fh)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}["drivegain.run"]
        attachments = {a.name: a.data for a in reader.iter_attachments()}
    assert meta["format_version"] == "1" and meta["run"] == "loaded"
    assert meta["payload"] == "calibrated-4590g" and meta["sync_period_s"] == "0.004"
    assert json.loads(meta["joint_names"]) == [f"j{i}" for i in range(1, 7)]
    assert attachments["tx40.toml"] == resource_path("tx40.toml").read_bytes()
    assert attachments["calibrated-4590g.toml"] == payload.read_bytes()
    assert attachments["short.json"] == short_trajectory.read_bytes()

    texts = [e["text"] for e in msgs["/events"]]
    phases = [t for t in texts if t.startswith("phase ")]
    assert phases == ["phase approach", "phase excitation", "phase retreat"]
    assert texts[-1] == f"run finished: {res.cycles} cycles"
    assert "cycle statistics" in texts

    # the setpoints are the planned motion (planned independently here from the start pose)
    log = read_run(out)
    motion = plan_excitation(load_trajectory(short_trajectory), cfg.robot, log.position[0])
    q_plan, _, _ = motion.sample(log.t)
    np.testing.assert_allclose(log.setpoint, q_plan, atol=2e-4)
    # the identification finds the excitation's start (its phase 0) from the phase event
    start = next(t0 for ph, t0, _ in motion.segments if ph is Phase.EXCITATION)
    assert excitation_start(log) == pytest.approx(start, abs=2 * 0.004)
    # ...the robot followed them, and it ends at rest where it started
    lag = np.abs(log.setpoint[:-1] - log.position[1:]).max(axis=0)
    assert np.all(lag < 0.02), lag
    np.testing.assert_allclose(log.position[-1], log.position[0], atol=2e-3)
    raw = msgs["/drives/raw"][100]["raw"]
    assert set(raw) >= {"position", "statusword", "torque_demand", "sync_counter"}


FAULTS = [
    ({"kind": "emcy", "node": 3, "at_s": 1.0}, DriveError, 3, 0x8611),
    ({"kind": "fault", "node": 2, "at_s": 1.0}, DriveError, 2, 0x2310),
    ({"kind": "heartbeat_stop", "node": 5, "at_s": 1.0}, DriveError, 5, None),
    ({"kind": "tpdo_missing", "node": 4, "at_s": 1.0}, DriveError, 4, 0x8250),
    ({"kind": "tpdo_late", "node": 6, "at_s": 1.0, "delay_s": 0.6}, DriveError, 6, 0x8250),
    ({"kind": "bus_error", "at_s": 1.0}, BusError, None, None),
]


@pytest.mark.parametrize(("fault", "exc_type", "node", "code"), FAULTS, ids=lambda x: str(x))
def test_fault_mid_run_quick_stops_and_ends_the_log(
    tmp_path: Path,
    make_config: Callable[..., Path],
    short_trajectory: Path,
    fault: dict,
    exc_type: type,
    node: int | None,
    code: int | None,
) -> None:
    cfg = load_acquisition_config(make_config(faults=[fault], acquisition="tpdo_timeout_s = 0.3"))
    out = tmp_path / "run.mcap"
    prepared = prepare_run(cfg, RunRequest(short_trajectory, out))
    rig = Rig(cfg)
    master = rig.open()
    try:
        session = Session(cfg, master, prepared, pre_events=rig.boot_events)
        session.plan()
        with pytest.raises(exc_type) as e:
            session.run()
        # every drive was quick-stopped: none follows targets any more
        assert rig.cell is not None
        assert all(d.state != State.OPERATION_ENABLED for d in rig.cell.drives.values())
        fired = rig.cell.fault_log()
        assert len(fired) == 1
    finally:
        rig.close()
    assert e.value.node == node
    if code is not None:
        assert e.value.code == code
    assert session.state is RunState.FAULT
    # the log is finished (not .part), complete up to the fault, the fault last
    assert out.exists() and not out.with_name("run.mcap.part").exists()
    msgs = _messages(out)
    cycles = [m["cycle"] for m in msgs["/joint_states"]]
    assert cycles == list(range(len(cycles)))
    t_last = cycles[-1] * cfg.period_s
    assert fired[0].sim_time_s - 2 * cfg.period_s <= t_last < motion_end(session)
    last = msgs["/events"][-1]
    assert last["level"] == EventLevel.ERROR and last["node"] == node
    assert last["action"] == "quick stop"
    if code is not None:
        assert last["code"] == code
    assert read_run(out).cycle[-1] == cycles[-1]


def motion_end(session: Session) -> float:
    assert session.motion is not None
    return session.motion.duration_s


def test_cli_exit_status_of_a_fault(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    cfg = make_config(faults=[{"kind": "emcy", "node": 1, "at_s": 0.8}])
    out = tmp_path / "run.mcap"
    status = main(
        ["acquire", "--config", str(cfg), "--trajectory", str(short_trajectory), "--out", str(out)]
    )
    assert status == 1
    assert read_run(out).events[-1]["level"] == EventLevel.ERROR


def test_a_drive_that_never_boots_writes_nothing(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    cfg = load_acquisition_config(make_config(faults=[{"kind": "never_boots", "node": 4}]))
    out = tmp_path / "run.mcap"
    with pytest.raises(DriveError) as e:
        run_foreground(cfg, RunRequest(short_trajectory, out), progress=False)
    assert e.value.node == 4
    assert not list(tmp_path.glob("run.mcap*"))


def test_late_tpdos_are_counted_not_fatal(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    cfg = load_acquisition_config(
        make_config(
            faults=[{"kind": "tpdo_late", "node": 2, "at_s": 2.5, "delay_s": 0.006}],
            acquisition="tpdo_timeout_s = 0.5",
        )
    )
    res = run_foreground(cfg, RunRequest(short_trajectory, tmp_path / "r.mcap"), progress=False)
    assert res.state is RunState.FINISHED
    assert int(res.stats["late_cycles"]) > 50  # every cycle from 2.5 s on
    log = read_run(res.path)  # type: ignore[arg-type]
    stats = next(e for e in log.events if e["text"] == "cycle statistics")
    assert stats["late_cycles"] == int(res.stats["late_cycles"])  # a number in the log
    assert np.all(np.diff(log.cycle) == 1)


def test_following_error_supervision_quick_stops(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    cfg = load_acquisition_config(make_config(acquisition="following_error = 0.002"))
    out = tmp_path / "run.mcap"
    with pytest.raises(SupervisionFault, match="following error") as e:
        run_foreground(cfg, RunRequest(short_trajectory, out), progress=False)
    last = read_run(out).events[-1]
    assert last["level"] == EventLevel.ERROR and last["node"] == e.value.node
    assert "following error" in last["text"]


def test_operator_stop_decelerates_to_rest(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    cfg = load_acquisition_config(make_config())
    out = tmp_path / "run.mcap"
    stop = StopRequest()
    prepared = prepare_run(cfg, RunRequest(short_trajectory, out))
    with Rig(cfg) as master:

        def on_cycle(s: Session) -> None:
            if s.cycle == 300:  # in the excitation, moving
                stop.request("SIGTERM")

        session = Session(cfg, master, prepared, stop=stop, on_cycle=on_cycle)
        session.plan()
        res = session.run()
    assert res.state is RunState.STOPPED and res.stop_reason == "SIGTERM"
    log = read_run(out)
    assert np.all(np.diff(log.cycle) == 1) and not log.truncated
    texts = [e["text"] for e in log.events]
    assert texts[-1].startswith("operator stop (SIGTERM): robot at rest")
    assert any(t.startswith("operator stop (SIGTERM): decelerating") for t in texts)
    # the setpoint comes to rest without a jump: velocity and acceleration within the limits
    dt = cfg.period_s
    v = np.diff(log.setpoint, axis=0) / dt
    a = np.diff(v, axis=0) / dt
    assert np.all(np.abs(v) <= cfg.robot.velocity_limits * 1.001)
    assert np.all(np.abs(a) <= cfg.robot.acceleration_limits * 1.01)
    np.testing.assert_allclose(v[-10:], 0.0, atol=1e-9)
    assert log.cycle[-1] < 700  # stopped well before the planned end (~800 cycles)


def test_bus_load_refused_and_warned(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    cfg = load_acquisition_config(make_config(period_s=0.002))  # 500 Hz: 125 % of 1 Mbit/s
    with pytest.raises(ConfigError, match=r"acquisition\.period_s.*needs 1\d\d%"):
        prepare_run(cfg, RunRequest(short_trajectory, tmp_path / "a.mcap"))
    assert not list(tmp_path.glob("a.mcap*"))
    cfg = load_acquisition_config(make_config(period_s=0.003))  # 83 %: allowed with a warning
    prepared = prepare_run(cfg, RunRequest(short_trajectory, tmp_path / "b.mcap"))
    assert prepared.warnings and "above 70%" in prepared.warnings[0]


def test_bad_inputs_are_refused_before_anything_is_written(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    cfg = load_acquisition_config(make_config())
    wild = json.loads(short_trajectory.read_text())
    wild["fourier"]["a"][0][0] = 40.0  # 40 rad/s on joint 1
    bad = tmp_path / "wild.json"
    bad.write_text(json.dumps(wild))
    with pytest.raises(DataError, match=r"wild\.json: outside the robot's limits: .*j1"):
        prepare_run(cfg, RunRequest(bad, tmp_path / "x.mcap"))
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"keep me")
    with pytest.raises(InputError, match="already exists"):
        prepare_run(cfg, RunRequest(short_trajectory, existing))
    assert existing.read_bytes() == b"keep me"
    with pytest.raises(InputError, match="label"):
        prepare_run(cfg, RunRequest(short_trajectory, tmp_path / "y.mcap", label="a b/c"))
    status = main(
        [
            "acquire",
            "--config",
            str(make_config()),
            "--trajectory",
            str(tmp_path / "none.json"),
            "--out",
            str(tmp_path / "z.mcap"),
        ]
    )
    assert status == 2
    assert sorted(p.name for p in tmp_path.iterdir() if "mcap" in p.name) == ["old.mcap"]
