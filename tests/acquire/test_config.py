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


def test_systemd_unit_is_type_notify() -> None:
    unit = resource_path("systemd/drivegain.service").read_text()
    assert "Type=notify" in unit and "WatchdogSec=" in unit
    assert "drivegain daemon --config" in unit


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
        ("", "[daemon]\noutput_dir = 'x'", "key 'daemon.socket': missing"),
        ("", "[daemon]\nsocket = 's'\noutput_dir = 'x'\nlog_format = 'xml'", "daemon.log_format"),
        ("", "[simulation]\nclock = 'fast'", "key 'simulation.clock'"),
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
