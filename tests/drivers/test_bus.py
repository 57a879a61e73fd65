"""Bus configuration, bus factory and the bus-load arithmetic."""

from __future__ import annotations

import pytest

from drivegain.config._toml import Table
from drivegain.drivers.bus import (
    TPDO_TIMEOUT_LOCKSTEP_S,
    BusConfig,
    bus_config_from_table,
    bus_load,
    default_tpdo_timeout,
    frame_bits,
    open_network,
)
from drivegain.drivers.clock import Clock
from drivegain.drivers.master import Master
from drivegain.errors import BusError, ConfigError, UsageError


def table(data: dict) -> Table:
    return Table(data, "acq.toml", "bus")


def test_bus_table():
    cfg = bus_config_from_table(
        table({"interface": "socketcan", "channel": "can0", "bitrate": 500_000})
    )
    assert cfg == BusConfig("socketcan", "can0", 500_000, {})
    cfg = bus_config_from_table(
        table({"interface": "kvaser", "channel": 0, "options": {"fd": False}})
    )
    assert (cfg.channel, cfg.bitrate, cfg.extra) == ("0", 1_000_000, {"fd": False})


@pytest.mark.parametrize(
    ("data", "key"),
    [
        ({"interface": "canbus9000", "channel": "x"}, "bus.interface"),
        ({"interface": "virtual"}, "bus.channel"),
        ({"interface": "virtual", "channel": "x", "bitrate": 300_000}, "bus.bitrate"),
        ({"interface": "virtual", "channel": "x", "speed": 1}, "bus.speed"),
        ({"interface": "virtual", "channel": True}, "bus.channel"),
        (
            {"interface": "virtual", "channel": "x", "options": {"channel": "y"}},
            "bus.options.channel",
        ),
    ],
)
def test_bad_bus_table_names_the_key(data, key):
    with pytest.raises(ConfigError) as err:
        bus_config_from_table(table(data))
    assert err.value.key == key and err.value.file == "acq.toml"
    assert "\n" not in str(err.value)


def test_tpdo_timeout_defaults_per_clock():
    assert default_tpdo_timeout(Clock.LOCKSTEP, 0.004) == TPDO_TIMEOUT_LOCKSTEP_S
    assert default_tpdo_timeout(Clock.REALTIME, 0.004) == pytest.approx(0.02)
    assert default_tpdo_timeout(Clock.REALTIME, 0.001) == pytest.approx(0.01)  # floor


def test_open_network_on_the_virtual_bus(channel):
    network = open_network(BusConfig("virtual", channel))
    try:
        assert network.bus is not None and network.notifier is not None
    finally:
        network.disconnect()


def test_open_network_failure_is_a_bus_error():
    with pytest.raises(BusError, match="cannot open CAN socketcan"):
        open_network(BusConfig("socketcan", "no-such-can-interface-42"))


def test_frame_bits_match_the_can_frame_format():
    # CAN 2.0A data frame, field by field: SOF, identifier, RTR, IDE, r0, DLC, data, CRC,
    # CRC delimiter, ACK slot + delimiter, EOF, intermission.
    def unstuffed(n: int) -> int:
        return 1 + 11 + 1 + 1 + 1 + 4 + 8 * n + 15 + 1 + 2 + 7 + 3

    assert unstuffed(8) == 111 == frame_bits(8, worst_case=False)
    # Worst case: one stuff bit after every 4 equal bits of SOF..CRC (34 + 8n bits).
    assert frame_bits(8) == 111 + (34 + 64 - 1) // 4 == 135  # design.md: 111 and 135 bits
    assert frame_bits(0) == 47 + 8
    assert frame_bits(8, extended=True) == 131 + (54 + 64 - 1) // 4
    with pytest.raises(UsageError):
        frame_bits(9)


def test_bus_load_of_six_drives():
    # 6 drives x (RPDO 8 B + 2 TPDO 8 B) + SYNC with counter (1 B): 18 x 135 + 65 bits.
    load = bus_load(6, 0.004, 1_000_000)
    assert load.bits_per_cycle == 18 * 135 + 65 == 2495
    assert load.max_rate_hz == pytest.approx(400.8, abs=0.05)
    assert load.load == pytest.approx(2495 * 250 / 1e6)  # 62 % at the default 250 Hz
    assert load.rate_at(0.7) == pytest.approx(280.6, abs=0.05)
    # design.md quotes ~2 250 bits and ~445 Hz for this exchange: 18 frames of 135 bits alone
    # are 2 430 bits, so the worst case is 401 Hz (and ~445 Hz needs 2 247 bits).
    assert load.max_rate_hz < 445.0
    # design.md's ~445 Hz lies between the stuffing-free and the worst-case figures: it assumes
    # about half the worst-case stuff bits (18 frames of ~123 bits). Both bounds bracket it.
    no_stuff = 18 * frame_bits(8, worst_case=False) + frame_bits(1, worst_case=False)
    assert no_stuff == 18 * 111 + 55
    assert 1e6 / load.bits_per_cycle < 445.0 < 1e6 / no_stuff
    assert bus_load(6, 0.004, 500_000).load == pytest.approx(2 * load.load)
    assert bus_load(6, 0.004, 1_000_000, sync=False).bits_per_cycle == 18 * 135


def test_master_bus_load_uses_its_pdo_mapping(tx40, channel):
    network = open_network(BusConfig("virtual", channel))
    try:
        master = Master(tx40, network, period_s=0.004)
        load = master.bus_load(1_000_000)
        master.close()
    finally:
        network.disconnect()
    # RPDO: target + controlword = 6 bytes (115 bits); TPDOs 8 + 8 bytes.
    assert load.bits_per_cycle == 6 * (115 + 135 + 135) + 65
    assert load.max_rate_hz == pytest.approx(1e6 / 2375)
