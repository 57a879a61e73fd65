"""The bus of an acquisition: the [bus] table, python-can's own configuration without it, and
the command line's --interface/--channel/--bitrate over either."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivegain.acquire.config import load_acquisition_config
from drivegain.config import resource_path
from drivegain.drivers.bus import BusOverrides
from drivegain.errors import ConfigError


def _hardware_toml(tmp_path: Path, with_bus: bool) -> Path:
    text = resource_path("acquire-can0.toml").read_text()
    text = text.replace('robot = "tx40.toml"', f'robot = "{resource_path("tx40.toml")}"')
    if not with_bus:  # drop the lines of the [bus] table, up to the next table
        lines, keep, inside = text.splitlines(), [], False
        for line in lines:
            if line.startswith("["):
                inside = line.strip() == "[bus]"
            if not inside:
                keep.append(line)
        text = "\n".join(keep) + "\n"
    path = tmp_path / "acq.toml"
    path.write_text(text)
    return path


def test_without_bus_table_python_cans_configuration_is_used(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = _hardware_toml(tmp_path, with_bus=False)
    assert "\n[bus]\n" not in path.read_text()
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/.can of the machine
    monkeypatch.setenv("CAN_INTERFACE", "socketcan")
    monkeypatch.setenv("CAN_CHANNEL", "can1")
    monkeypatch.setenv("CAN_BITRATE", "500000")
    bus = load_acquisition_config(path).bus
    assert (bus.interface, bus.channel, bus.bitrate) == ("socketcan", "can1", 500000)
    (tmp_path / ".can").write_text("[default]\ninterface = pcan\nchannel = PCAN_USBBUS1\n")
    for var in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE"):
        monkeypatch.delenv(var)
    bus = load_acquisition_config(path).bus
    assert (bus.interface, bus.channel) == ("pcan", "PCAN_USBBUS1")


def test_without_any_bus_configuration_the_error_says_where_it_looked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = _hardware_toml(tmp_path, with_bus=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    for var in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(var, raising=False)
    if Path("/etc/can.conf").exists():
        pytest.skip("this machine has an /etc/can.conf")
    with pytest.raises(ConfigError) as exc:
        load_acquisition_config(path)
    assert str(path) in str(exc.value) and "no [bus] table" in str(exc.value)


def test_command_line_overrides_win_and_are_checked(tmp_path: Path) -> None:
    path = _hardware_toml(tmp_path, with_bus=True)
    bus = load_acquisition_config(path, BusOverrides(channel="can7", bitrate=500_000)).bus
    assert (bus.interface, bus.channel, bus.bitrate) == ("socketcan", "can7", 500_000)
    with pytest.raises(ConfigError, match="--bitrate"):
        load_acquisition_config(path, BusOverrides(bitrate=123))
    with pytest.raises(ConfigError, match="unknown python-can interface"):
        load_acquisition_config(path, BusOverrides(interface="nonsense"))
