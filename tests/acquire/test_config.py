"""The acquisition TOML: shipped examples load, mistakes get one line naming file and key."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivegain.acquire.config import (
    AcquisitionSettings,
    DaemonSettings,
    SupervisionSettings,
    load_acquisition_config,
)
from drivegain.config import resource_path
from drivegain.config.payload import PayloadTable
from drivegain.config.robot import MDH, Joint, Robot
from drivegain.config.schema import declared, default_of, describe, keys_of
from drivegain.config.truth import LinkTruth, Truth
from drivegain.drivers.bus import (
    TPDO_TIMEOUT_LOCKSTEP_S,
    TPDO_TIMEOUT_REALTIME_PERIODS,
    BusConfig,
)
from drivegain.drivers.clock import Clock
from drivegain.drivers.faults import FaultSpec
from drivegain.drivers.simconfig import SimConfig
from drivegain.errors import ConfigError


def test_shipped_configs_load() -> None:
    sim = load_acquisition_config(resource_path("acquire-sim.toml"))
    assert sim.clock is Clock.LOCKSTEP and sim.bus.interface == "virtual"
    assert sim.tpdo_timeout_s == TPDO_TIMEOUT_LOCKSTEP_S
    assert sim.simulation is not None and sim.simulation.current_noise_nm == pytest.approx(0.05)
    assert sim.period_s == pytest.approx(0.004)
    hw = load_acquisition_config(resource_path("acquire-can0.toml"))
    assert hw.clock is Clock.REALTIME and hw.simulation is None
    assert hw.tpdo_timeout_s == pytest.approx(TPDO_TIMEOUT_REALTIME_PERIODS * hw.period_s)
    assert (hw.bus.interface, hw.bus.channel, hw.bus.bitrate) == ("socketcan", "can0", 1_000_000)
    assert hw.daemon is not None and hw.daemon.log_format == "json"
    assert hw.robot.name == sim.robot.name
    rt = load_acquisition_config(resource_path("acquire-sim-realtime.toml"))
    assert rt.clock == "realtime" and rt.bus.interface == "drivegain-ipc"
    assert rt.simulation is not None and rt.rt_priority == 80
    assert (rt.spin_s, hw.spin_s) == (0.0, pytest.approx(3e-4))


def test_systemd_unit_is_type_notify() -> None:
    unit = resource_path("systemd/drivegain.service").read_text()
    assert "Type=notify" in unit and "WatchdogSec=" in unit
    assert "drivegain daemon --config" in unit
    # the daemon's connections need descriptors: the unit says how many, not the distro default
    limit = [line for line in unit.splitlines() if line.startswith("LimitNOFILE=")]
    assert limit and int(limit[0].split("=")[1]) >= 256


def test_daemon_limits_are_settings_with_defaults() -> None:
    sim = load_acquisition_config(resource_path("acquire-sim.toml"))
    assert sim.daemon is not None
    assert sim.daemon.max_clients == default_of(DaemonSettings, "max_clients") == 16
    assert sim.daemon.client_idle_s == default_of(DaemonSettings, "client_idle_s") == 300.0
    assert sim.daemon.client_buffer_bytes == 1 << 20


def test_a_fault_on_a_node_the_robot_does_not_have_names_file_and_key(tmp_path: Path) -> None:
    """Shipped config with absolute paths plus a fault on node 7 (the TX-40 has nodes 1-6)."""
    text = resource_path("acquire-sim.toml").read_text()
    text = text.replace('"tx40.toml"', f'"{resource_path("tx40.toml")}"')
    text = text.replace('"sim/tx40-truth.toml"', f'"{resource_path("sim/tx40-truth.toml")}"')
    ok = '[[simulation.fault]]\nkind = "emcy"\nnode = 3\nat_s = 1.0\n'
    bad = '[[simulation.fault]]\nkind = "heartbeat_stop"\nnode = 7\nat_s = 1.0\n'
    p = tmp_path / "acq.toml"
    p.write_text(text + ok + bad)
    with pytest.raises(ConfigError) as e:
        load_acquisition_config(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: key 'simulation.fault[1].node': ") and "node id 7" in msg, msg
    assert "1, 2, 3, 4, 5, 6" in msg and "\n" not in msg
    p.write_text(text + ok)
    assert load_acquisition_config(p).simulation is not None


BASE = """
[acquisition]
robot = "{robot}"
{acq}
[bus]
interface = "virtual"
channel = "x"
{extra}
"""


@pytest.mark.parametrize(
    ("acq", "extra", "message"),
    [
        ("period_s = 0", "", "key 'acquisition.period_s': must be > 0"),
        ("period_s = 0.5", "", "key 'acquisition.period_s': must be between"),
        ("perod_s = 0.004", "", "key 'acquisition.perod_s': unknown key"),
        ("following_error = [0.1, 0.1]", "", "key 'acquisition.following_error': expected 6"),
        ("following_error = -1.0", "", "key 'acquisition.following_error': must be > 0"),
        ("velocity_margin = 0.5", "", "key 'acquisition.velocity_margin': must be >= 1"),
        ("rt_priority = 120", "", "key 'acquisition.rt_priority'"),
        ("spin_s = -0.001", "", "key 'acquisition.spin_s': must be between 0 and 0.01 s"),
        ("spin_s = 0.5", "", "key 'acquisition.spin_s': must be between 0 and 0.01 s"),
        ("", "[daemon]\noutput_dir = 'x'", "key 'daemon.socket': missing"),
        ("", "[daemon]\nsocket = 's'\noutput_dir = 'x'\nlog_format = 'xml'", "daemon.log_format"),
        ("", "[simulation]\nclock = 'fast'", "key 'simulation.clock'"),
        ("", "[daemon]\nsocket = 's'\noutput_dir = 'x'\nmax_clients = 0", "daemon.max_clients"),
        ("", "[daemon]\nsocket = 's'\noutput_dir = 'x'\nclient_idle_s = 0", "client_idle_s"),
        (
            "",
            "[daemon]\nsocket = 's'\noutput_dir = 'x'\nclient_buffer_bytes = 10",
            "daemon.client_buffer_bytes",
        ),
    ],
)
def test_bad_config_one_line(tmp_path: Path, acq: str, extra: str, message: str) -> None:
    p = tmp_path / "acq.toml"
    p.write_text(BASE.format(robot=resource_path("tx40.toml"), acq=acq, extra=extra))
    with pytest.raises(ConfigError) as e:
        load_acquisition_config(p)
    text = str(e.value)
    assert message in text and str(p) in text and "\n" not in text


def test_missing_robot_file(tmp_path: Path) -> None:
    p = tmp_path / "acq.toml"
    p.write_text(BASE.format(robot="nope.toml", acq="", extra=""))
    with pytest.raises(ConfigError, match=r"key 'acquisition.robot': file not found"):
        load_acquisition_config(p)


def test_every_shipped_table_declares_a_doc_for_each_key() -> None:
    """Each table is declared once, with a one-line doc per key (for help and docs)."""
    tables = (AcquisitionSettings, SupervisionSettings, DaemonSettings, BusConfig, SimConfig)
    tables += (FaultSpec, Robot, Joint, MDH, PayloadTable, Truth, LinkTruth)
    for cls in tables:
        assert keys_of(cls), cls
        assert all(d.spec.doc for d in declared(cls)), cls
        assert len(describe(cls)) == len(keys_of(cls))
    assert "period_s (default 0.004, s): SYNC period" in describe(AcquisitionSettings)
    assert default_of(SimConfig, "clock") is Clock.LOCKSTEP


def test_simulated_drives_may_use_vcan_never_a_real_can_device(tmp_path: Path) -> None:
    from drivegain.acquire.config import load_acquisition_config

    text = resource_path("acquire-sim.toml").read_text()
    text = text.replace('robot = "tx40.toml"', f'robot = "{resource_path("tx40.toml")}"')
    text = text.replace(
        'truth = "sim/tx40-truth.toml"', f'truth = "{resource_path("sim/tx40-truth.toml")}"'
    )
    for channel, allowed in (("vcan0", True), ("vcan-test", True), ("can0", False)):
        path = tmp_path / f"{channel}.toml"
        path.write_text(
            text.replace('interface = "virtual"', 'interface = "socketcan"').replace(
                'channel = "drivegain-sim"', f'channel = "{channel}"'
            )
        )
        if allowed:
            assert load_acquisition_config(path).bus.channel == channel
        else:
            with pytest.raises(ConfigError, match="simulated drives never go on a real bus"):
                load_acquisition_config(path)
