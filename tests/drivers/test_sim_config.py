"""The [simulation] table and the checks of the simulated cell's configuration."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from drivegain.config import resource_path
from drivegain.config._toml import Table
from drivegain.config.robot import WristFriction
from drivegain.drivers.bus import BusConfig
from drivegain.drivers.clock import Clock
from drivegain.drivers.faults import FaultKind, FaultSpec
from drivegain.drivers.sim import SimConfig, SimulatedCell
from drivegain.drivers.simconfig import sim_config_from_table
from drivegain.errors import ConfigError


def parse(text: str, base: Path) -> SimConfig:
    return sim_config_from_table(
        Table(tomllib.loads(text)["simulation"], "acq.toml", "simulation"), base
    )


def test_defaults(tmp_path):
    cfg = parse("[simulation]\n", tmp_path)
    assert cfg == SimConfig()
    assert cfg.truth == resource_path("sim/tx40-truth.toml")
    assert (cfg.clock, cfg.payload, cfg.faults, cfg.friction) == (Clock.LOCKSTEP, None, (), None)


def test_every_key(tmp_path):
    (tmp_path / "truth.toml").write_bytes(resource_path("sim/tx40-truth.toml").read_bytes())
    cfg = parse(
        """
        [simulation]
        clock = "realtime"
        truth = "truth.toml"
        payload = "payloads/calibrated-4590g.toml"   # not beside the file: a shipped one
        seed = 4
        current_noise_nm = 0.25
        friction = "paper"
        initial_position = [0.0, 0.1, 0.2, 0.0, 0.3, 0.0]
        max_step_s = 0.00025
        bandwidth_hz = 40.0
        history_s = 30.0
        [[simulation.fault]]
        kind = "emcy"
        node = 3
        at_s = 1.5
        code = 0x8611
        [[simulation.fault]]
        kind = "tpdo_late"
        node = 2
        delay_s = 0.01
        tpdo = 1
        [[simulation.fault]]
        kind = "bus_error"
        at_s = 2.0
        """,
        tmp_path,
    )
    assert cfg.truth == tmp_path / "truth.toml"
    assert cfg.payload == resource_path("payloads/calibrated-4590g.toml")
    assert (cfg.clock, cfg.seed, cfg.current_noise_nm, cfg.friction) == (
        "realtime",
        4,
        0.25,
        "paper",
    )
    assert cfg.initial_position == (0.0, 0.1, 0.2, 0.0, 0.3, 0.0)
    assert (cfg.max_step_s, cfg.bandwidth_hz, cfg.history_s) == (0.00025, 40.0, 30.0)
    assert cfg.faults == (
        FaultSpec(FaultKind.EMCY, node=3, at_s=1.5, code=0x8611),
        FaultSpec(FaultKind.TPDO_LATE, node=2, delay_s=0.01, tpdo=1),
        FaultSpec(FaultKind.BUS_ERROR, at_s=2.0),
    )


@pytest.mark.parametrize(
    ("body", "key"),
    [
        ('clock = "fast"', "simulation.clock"),
        ('truth = "missing.toml"', "simulation.truth"),
        ("current_noise_nm = -1.0", "simulation.current_noise_nm"),
        ("seed = -1", "simulation.seed"),
        ('friction = "stribeck"', "simulation.friction"),
        ("noise = 1", "simulation.noise"),
        ('[[simulation.fault]]\nkind = "explode"\nnode = 1', "simulation.fault[0].kind"),
        ('[[simulation.fault]]\nkind = "emcy"', "simulation.fault[0].node"),
        ('[[simulation.fault]]\nkind = "tpdo_late"\nnode = 1', "simulation.fault[0].delay_s"),
        ('[[simulation.fault]]\nkind = "bus_error"\nnode = 1', "simulation.fault[0].node"),
        (
            '[[simulation.fault]]\nkind = "emcy"\nnode = 1\ncode = 0x10000',
            "simulation.fault[0].code",
        ),
        ('[[simulation.fault]]\nkind = "emcy"\nnode = 1\nwhen = 2', "simulation.fault[0].when"),
    ],
)
def test_bad_simulation_table_names_the_key(tmp_path, body, key):
    with pytest.raises(ConfigError) as err:
        parse("[simulation]\n" + body + "\n", tmp_path)
    assert err.value.key == key
    assert "\n" not in str(err.value)


def test_cell_checks_its_configuration(tx40):
    bus = BusConfig("virtual", "unused")
    with pytest.raises(ConfigError, match="node id 9"):
        SimulatedCell(tx40, bus, SimConfig(faults=(FaultSpec(FaultKind.EMCY, node=9),)), 0.004)
    with pytest.raises(ConfigError, match="outside the joint limits"):
        SimulatedCell(tx40, bus, SimConfig(initial_position=(4.0, 0, 0, 0, 0, 0)), 0.004)
    with pytest.raises(ConfigError, match="too high for the internal step"):
        SimulatedCell(tx40, bus, SimConfig(max_step_s=0.004), 0.008)
    cell = SimulatedCell(tx40, bus, SimConfig(), 0.001)
    assert cell.substeps == 2 and cell.dt == pytest.approx(0.0005)


def test_cell_rejects_an_eds_without_the_drive_objects(tx40, tmp_path):
    text = resource_path("cia402-servo.eds").read_text()
    start = text.index("[6075]")
    eds = tmp_path / "partial.eds"
    eds.write_text(text[:start] + text[text.index("[6076]", start) :])
    with pytest.raises(ConfigError, match="0x6075") as err:
        SimulatedCell(tx40, BusConfig("virtual", "unused"), SimConfig(), 0.004, eds=eds)
    assert err.value.file == str(eds)


def test_clock_and_friction_are_enums(tmp_path):
    cfg = parse('[simulation]\nclock = "realtime"\nfriction = "paper"\n', tmp_path)
    assert cfg.clock is Clock.REALTIME and cfg.friction is WristFriction.PAPER
    # programs that build the table themselves may still pass strings
    assert SimConfig(clock="realtime", friction="physical") == SimConfig(
        clock=Clock.REALTIME, friction=WristFriction.PHYSICAL
    )
    with pytest.raises(ConfigError, match="simulation clock must be one of"):
        SimConfig(clock="fast")
    with pytest.raises(ConfigError, match="friction must be physical or paper"):
        SimConfig(friction="stribeck")
