"""Byte-exact scripts of what the master puts on the bus (in the style of canopen's SDO tests):
boot sequence, CiA 402 state machine, the cyclic exchange, quick stop, disable and close.

The expected frames are written from CiA 301/402, not from the code under test: SDO expedited
transfers (0x23/0x27/0x2B/0x2F download, 0x40 upload), NMT (0x000), SYNC (0x080), PDOs.
"""

from __future__ import annotations

import math
import struct
import time
from pathlib import Path

import pytest

from drivegain.drivers import objects as ob
from drivegain.drivers.cia402 import State
from drivegain.drivers.master import Master, MasterHeartbeat, Timeouts
from drivegain.errors import ConfigError, DriveError
from drivegain.formats.log import EventLevel

NODE = 1
PERIOD = 0.004
TIMEOUTS = Timeouts(boot_s=0.5, sdo_s=0.2, state_s=0.05, heartbeat_s=5.0, tpdo_s=0.2)


TAGGED_TPDO1 = (0x60640020, 0x60740010, 0x20100008, 0x10010008)
TAGGED_TPDO2 = (0x60410010, 0x60780010, 0x60770010, 0x20100008, 0x60610008)


def map_pdo(f, comm: int, mapping: int, cob: int, entries: tuple[int, ...]) -> list[tuple]:
    w = f.sdo_write
    return [
        *w(NODE, comm, 1, f.u32(0x80000000 | cob)),  # disable
        *w(NODE, comm, 2, f.u8(1)),  # synchronous, every SYNC
        *w(NODE, mapping, 0, f.u8(0)),  # clear
        *(frame for k, e in enumerate(entries, 1) for frame in w(NODE, mapping, k, f.u32(e))),
        *w(NODE, mapping, 0, f.u8(len(entries))),
        *w(NODE, comm, 1, f.u32(cob)),  # enable
    ]


#: 0x1016 sub 1 for the default master heartbeat: node 127 (0x7F) << 16 | 300 ms (3 periods).
DEFAULT_CONSUMER = bytes.fromhex("2C 01 7F 00")


#: TPDO mappings of a drive without the SYNC echo: position, torque demand, statusword; currents,
#: error register, mode.
NO_ECHO_TPDOS = (
    (0x60640020, 0x60740010, 0x60410010),
    (0x60780010, 0x60770010, 0x10010008, 0x60610008),
)


def no_echo_eds(tmp_path) -> Path:
    """The shipped drive EDS without object 0x2010 (the SYNC echo), written in ``tmp_path``."""
    text = ob.default_eds().read_text()
    eds = tmp_path / "no-echo.eds"
    start = text.index("[2010]")
    eds.write_text(text[:start] + text[text.index("[603F]", start) :])
    return eds


def boot_script(
    f, tpdo1=TAGGED_TPDO1, tpdo2=TAGGED_TPDO2, consumer=DEFAULT_CONSUMER
) -> list[tuple]:
    w, r = f.sdo_write, f.sdo_read
    s: list[tuple] = [
        (f.TX, 0x000, bytes([0x82, 0x01])),  # NMT reset communication, node 1
        (f.RX, 0x701, bytes([0x00])),  # boot-up
        # The frames of the first SDO written out, the rest built by the helpers.
        (f.TX, 0x601, bytes.fromhex("40 00 10 00 00 00 00 00")),  # read device type
        (f.RX, 0x581, bytes.fromhex("43 00 10 00 92 01 02 00")),  # 0x00020192: CiA 402 servo
        *r(NODE, 0x6502, 0, f.u32(0x80)),  # supported modes: CSP
        *r(NODE, 0x6075, 0, f.u32(6000)),  # rated current, mA
        *r(NODE, 0x608F, 1, f.u32(196608)),  # encoder increments
        *r(NODE, 0x608F, 2, f.u32(1)),  # per motor revolution
        # Unused PDOs off: RPDO2-4, TPDO3-4 (bit 31 set on the predefined COB-IDs).
        (f.TX, 0x601, bytes.fromhex("23 01 14 01 01 03 00 80")),
        (f.RX, 0x581, bytes.fromhex("60 01 14 01 00 00 00 00")),
        *w(NODE, 0x1402, 1, f.u32(0x80000401)),
        *w(NODE, 0x1403, 1, f.u32(0x80000501)),
        *w(NODE, 0x1802, 1, f.u32(0x80000381)),
        *w(NODE, 0x1803, 1, f.u32(0x80000481)),
        # RPDO1: disable, synchronous, clear, map target (i32) + controlword (u16), enable.
        *w(NODE, 0x1400, 1, f.u32(0x80000201)),
        *w(NODE, 0x1400, 2, f.u8(1)),
        *w(NODE, 0x1600, 0, f.u8(0)),
        *w(NODE, 0x1600, 1, f.u32(0x607A0020)),
        *w(NODE, 0x1600, 2, f.u32(0x60400010)),
        *w(NODE, 0x1600, 0, f.u8(2)),
        *w(NODE, 0x1400, 1, f.u32(0x00000201)),
        # TPDO1 (default: position actual, torque demand, SYNC echo, error register) and
        # TPDO2 (statusword, current actual, torque actual, SYNC echo, mode display).
        *map_pdo(f, 0x1800, 0x1A00, 0x181, tpdo1),
        *map_pdo(f, 0x1801, 0x1A01, 0x281, tpdo2),
        *w(NODE, 0x1019, 0, f.u8(240)),  # SYNC counter overflow
        (f.TX, 0x601, bytes.fromhex("2B 17 10 00 64 00 00 00")),  # heartbeat 100 ms
        (f.RX, 0x581, bytes.fromhex("60 17 10 00 00 00 00 00")),
        # Consumer of the master's heartbeat (0x1016 sub 1).
        (f.TX, 0x601, bytes.fromhex("23 16 10 01") + consumer),
        (f.RX, 0x581, bytes.fromhex("60 16 10 01 00 00 00 00")),
        *w(NODE, 0x60C2, 1, f.u8(4)),  # interpolation period 4 · 10^-3 s
        *w(NODE, 0x60C2, 2, f.i8(-3)),
        (f.TX, 0x601, bytes.fromhex("2F 60 60 00 08 00 00 00")),  # mode of operation: CSP
        (f.RX, 0x581, bytes.fromhex("60 60 60 00 00 00 00 00")),
        *r(NODE, 0x6061, 0, f.i8(8)),
        (f.TX, 0x000, bytes([0x01, 0x01])),  # NMT start
        (f.RX, 0x701, bytes([0x05])),  # heartbeat: OPERATIONAL
    ]
    return s


def close_script(f) -> list[tuple]:
    """close() of a booted drive at rest: its consumer of the master's heartbeat off (an orderly
    end is no fault), then NMT pre-operational."""
    return [
        (f.TX, 0x601, bytes.fromhex("23 16 10 01 00 00 00 00")),  # 0x1016:01 = 0
        (f.RX, 0x581, bytes.fromhex("60 16 10 01 00 00 00 00")),
        (f.TX, 0x000, bytes([0x80, 0x01])),  # NMT pre-operational
    ]


def enable_script(f, start_sw: int = 0x0240, position: int = 1234) -> list[tuple]:
    w, r = f.sdo_write, f.sdo_read
    return [
        *r(NODE, 0x6041, 0, f.u16(start_sw)),  # SWITCH_ON_DISABLED
        *r(NODE, 0x6064, 0, f.i32(position)),
        *w(NODE, 0x607A, 0, f.i32(position)),  # hold the actual position
        *r(NODE, 0x6041, 0, f.u16(0x0240)),
        *w(NODE, 0x6040, 0, f.u16(0x0006)),  # shutdown
        *r(NODE, 0x6041, 0, f.u16(0x0231)),  # READY_TO_SWITCH_ON
        *w(NODE, 0x6040, 0, f.u16(0x0007)),  # switch on
        *r(NODE, 0x6041, 0, f.u16(0x0233)),  # SWITCHED_ON
        *w(NODE, 0x6040, 0, f.u16(0x000F)),  # enable operation
        *r(NODE, 0x6041, 0, f.u16(0x1237)),  # OPERATION_ENABLED, following
    ]


def tpdos(f, counter: int, position: int, demand: int, current: int, sw: int) -> list[tuple]:
    return [
        (f.RX, 0x181, struct.pack("<ihBB", position, demand, counter, 0)),
        (f.RX, 0x281, struct.pack("<HhhBb", sw, current, current, counter, 8)),
    ]


def test_boot_sequence_is_byte_exact(one_joint_robot, scripted, frames):
    close = close_script(frames)
    rig = scripted(boot_script(frames) + close)
    master = Master(one_joint_robot, rig.network, period_s=PERIOD, timeouts=TIMEOUTS)
    master.boot()
    drained = master.drain_events()
    events = [e.text for e in drained]
    assert "NMT BOOT-UP" in events and "NMT OPERATIONAL" in events
    assert all(isinstance(e.level, EventLevel) for e in drained)
    master.close()
    assert rig.bus.mismatches == []
    assert rig.bus.remaining() == []


def test_master_heartbeat_and_the_drives_consumer_of_it_are_byte_exact(
    one_joint_robot, scripted, frames
):
    """Master node id 100, period 50 ms: COB-ID 0x764 carrying 0x05 (NMT operational), the first
    at the start of boot, then periodically until close; the drive's consumer entry 0x1016:01 =
    100 << 16 | 150 ms (three periods), switched off again (0) by close()."""
    consumer = bytes.fromhex("96 00 64 00")  # 0x00640096
    script = boot_script(frames, consumer=consumer) + close_script(frames)
    rig = scripted(script, background={0x764: bytes([0x05])})
    master = Master(
        one_joint_robot,
        rig.network,
        period_s=PERIOD,
        timeouts=TIMEOUTS,
        heartbeat=MasterHeartbeat(node_id=100, period_s=0.05),
    )
    start = time.monotonic()
    master.boot()
    time.sleep(0.25)
    master.close()
    closed = time.monotonic()
    assert rig.bus.mismatches == []
    assert rig.bus.remaining() == []
    beats = list(rig.bus.background_sent)
    assert all((cob, data) == (0x764, b"\x05") for _, cob, data in beats)
    assert beats and beats[0][0] - start < 0.05  # at once, before the drives are reset
    assert len(beats) >= 3  # periodic (0.25 s at 50 ms; counted loosely, the machine is shared)
    time.sleep(0.15)
    assert len(rig.bus.background_sent) == len(beats)  # silent once closed
    assert all(t <= closed for t, _, _ in rig.bus.background_sent)


def test_enable_cycle_quick_stop_disable_close_are_byte_exact(one_joint_robot, scripted, frames):
    f = frames
    q = 0.01  # rad at the joint -> motor 0.32 rad -> 10013.4 -> 10013 counts
    target_counts = round(q * 32 * 196608 / (2 * math.pi))
    assert target_counts == 10013
    script = [
        *boot_script(f),
        *enable_script(f),
        # Cycle 0: RPDO1 (target, controlword 0x000F), SYNC with counter 1, both TPDOs.
        (f.TX, 0x201, struct.pack("<iH", target_counts, 0x000F)),
        (f.TX, 0x080, bytes([0x01])),
        *tpdos(f, 1, 10000, 125, 130, 0x1237),
        # Quick stop: by SDO, then cycles with controlword 0x0002 until the drive rests.
        *f.sdo_write(NODE, 0x6040, 0, f.u16(0x0002)),
        (f.TX, 0x201, struct.pack("<iH", target_counts, 0x0002)),
        (f.TX, 0x080, bytes([0x02])),
        *tpdos(f, 2, 10010, 40, 41, 0x0217),  # QUICK_STOP_ACTIVE
        (f.TX, 0x201, struct.pack("<iH", target_counts, 0x0002)),
        (f.TX, 0x080, bytes([0x03])),
        *tpdos(f, 3, 10012, 0, 0, 0x0240),  # at rest: SWITCH_ON_DISABLED
        # close(): nothing powered any more -> no disable; NMT pre-operational.
        *close_script(f),
    ]
    rig = scripted(script)
    master = Master(one_joint_robot, rig.network, period_s=PERIOD, timeouts=TIMEOUTS)
    master.boot()
    master.enable()
    sample = master.cycle([q])
    assert sample.cycle == 0
    assert sample.raw["position"] == [10000] and sample.raw["sync_counter"] == [1]
    assert sample.raw["target"] == [target_counts]
    assert sample.position[0] == pytest.approx(10000 / 196608 * 2 * math.pi / 32, rel=1e-12)
    assert sample.current_reference[0] == pytest.approx(0.125 * 6.0)  # 125 per mille of 6 A
    assert sample.current[0] == pytest.approx(0.130 * 6.0)
    master.quick_stop()
    assert master.states[NODE] == State.SWITCH_ON_DISABLED
    master.close()
    assert rig.bus.mismatches == []
    assert rig.bus.remaining() == []


def test_fault_reset_uses_a_rising_edge(one_joint_robot, scripted, frames):
    f = frames
    script = [
        *boot_script(f),
        *f.sdo_read(NODE, 0x6041, 0, f.u16(0x0208)),  # FAULT
        *f.sdo_write(NODE, 0x6040, 0, f.u16(0x0000)),  # bit 7 low first...
        *f.sdo_write(NODE, 0x6040, 0, f.u16(0x0080)),  # ...then high: rising edge
        *f.sdo_read(NODE, 0x6041, 0, f.u16(0x0240)),  # SWITCH_ON_DISABLED
        *enable_script(f)[2:],  # position read, target, walk up
        # close() of an enabled drive: shutdown, check, NMT pre-operational.
        *f.sdo_write(NODE, 0x6040, 0, f.u16(0x0006)),
        *f.sdo_read(NODE, 0x6041, 0, f.u16(0x0231)),
        *close_script(f),
    ]
    rig = scripted(script)
    master = Master(one_joint_robot, rig.network, period_s=PERIOD, timeouts=TIMEOUTS)
    master.boot()
    master.enable()
    assert master.states[NODE] == State.OPERATION_ENABLED
    master.close()
    assert master.states[NODE] == State.READY_TO_SWITCH_ON
    assert rig.bus.mismatches == []
    assert rig.bus.remaining() == []


def test_a_stuck_transition_times_out_with_node_and_state(one_joint_robot, scripted, frames):
    f = frames
    poll = (0x601, bytes.fromhex("40 41 60 00 00 00 00 00"))
    stuck = (0x581, bytes.fromhex("4B 41 60 00 40 02 00 00"))  # stays SWITCH_ON_DISABLED
    script = [
        *boot_script(f),
        *enable_script(f)[:10],  # up to the shutdown command
        (f.TX_REPEAT, *poll, stuck),
        *f.sdo_read(NODE, 0x603F, 0, f.u16(0x5530)),  # the master asks for the error code
        *close_script(f),  # close()
    ]
    rig = scripted(script)
    master = Master(one_joint_robot, rig.network, period_s=PERIOD, timeouts=TIMEOUTS)
    master.boot()
    with pytest.raises(DriveError) as err:
        master.enable()
    assert err.value.node == NODE
    assert err.value.state is State.SWITCH_ON_DISABLED
    assert "state SWITCH_ON_DISABLED" in str(err.value)
    assert err.value.code == 0x5530
    assert "no transition out of SWITCH_ON_DISABLED" in str(err.value)
    master.close()
    assert rig.bus.mismatches == []
    assert rig.bus.remaining() == []


def test_no_boot_up_times_out_naming_the_node(one_joint_robot, scripted, frames):
    rig = scripted([(frames.TX, 0x000, bytes([0x82, 0x01]))])  # the drive stays silent
    master = Master(one_joint_robot, rig.network, period_s=PERIOD, timeouts=TIMEOUTS)
    with pytest.raises(DriveError) as err:
        master.boot()
    assert err.value.node == NODE and err.value.code == 0x8130
    assert "boot-up" in str(err.value)
    master.close()


def test_a_drive_that_refuses_csp_is_rejected(one_joint_robot, scripted, frames):
    f = frames
    script = boot_script(f)[:4] + f.sdo_read(NODE, 0x6502, 0, f.u32(0x01))  # profile position
    rig = scripted(script)
    master = Master(one_joint_robot, rig.network, period_s=PERIOD, timeouts=TIMEOUTS)
    with pytest.raises(DriveError, match="cyclic synchronous position") as err:
        master.boot()
    assert err.value.node == NODE
    master.close()


def test_drives_without_the_sync_echo_get_a_standard_mapping(
    one_joint_robot, scripted, frames, tmp_path
):
    """A drive EDS without 0x2010 (any drive of the market): only standard objects are mapped
    and the TPDOs of a cycle are those received between its SYNC and the deadline."""
    f = frames
    eds = no_echo_eds(tmp_path)
    plain1, plain2 = NO_ECHO_TPDOS
    script = [
        *boot_script(f, plain1, plain2),
        *enable_script(f),
        (f.TX, 0x201, struct.pack("<iH", 1234, 0x000F)),
        (f.TX, 0x080, bytes([0x01])),
        (f.RX, 0x181, struct.pack("<ihH", 1240, -50, 0x1237)),
        (f.RX, 0x281, struct.pack("<hhBb", -52, -52, 0, 8)),
        *f.sdo_write(NODE, 0x6040, 0, f.u16(0x0006)),  # close()
        *f.sdo_read(NODE, 0x6041, 0, f.u16(0x0231)),
        *close_script(f),
    ]
    rig = scripted(script)
    master = Master(one_joint_robot, rig.network, period_s=PERIOD, eds=eds, timeouts=TIMEOUTS)
    assert not master.layout.tagged
    master.boot()
    master.enable()
    sample = master.cycle([1234 / 196608 * 2 * math.pi / 32])
    assert sample.raw["position"] == [1240] and sample.raw["statusword"] == [0x1237]
    assert sample.current_reference[0] == pytest.approx(-0.050 * 6.0)
    master.close()
    assert rig.bus.mismatches == []
    assert rig.bus.remaining() == []


def _edit_eds(tmp_path, section: str, old: str, new: str):
    """A copy of the shipped EDS with ``old`` replaced by ``new`` in ``[section]`` only."""
    text = ob.default_eds().read_text()
    start = text.index(f"[{section}]")
    end = text.index("\n[", start + 1)
    eds = tmp_path / "edited.eds"
    eds.write_text(text[:start] + text[start:end].replace(old, new) + text[end:])
    return eds


@pytest.mark.parametrize(
    ("section", "old", "new", "message"),
    [
        ("1A01sub2", "AccessType=rw", "AccessType=ro", r"0x1A01:02 is read-only"),
        ("1600", "ObjectType=0x9", "ObjectType=0x8", r"0x1600 must be a RECORD"),
    ],
    ids=["read-only", "array"],
)
def test_an_eds_whose_mapping_canopen_cannot_write_is_refused_before_any_frame(
    one_joint_robot, scripted, tmp_path, section, old, new, message
):
    """canopen's PdoMap.save() would skip read-only entries silently, and write no entry of an
    ARRAY mapping, enabling a mapping the master cannot decode: refuse the EDS, naming it, and
    leave the network as it was."""
    eds = _edit_eds(tmp_path, section, old, new)
    rig = scripted([])
    with pytest.raises(ConfigError, match=message) as err:
        Master(one_joint_robot, rig.network, period_s=PERIOD, eds=eds, timeouts=TIMEOUTS)
    assert err.value.file == str(eds)
    assert rig.network.nodes == {} and rig.bus.sent == []


def test_an_eds_without_an_object_the_master_writes_is_refused(one_joint_robot, scripted, tmp_path):
    text = ob.default_eds().read_text()
    start = text.index("[603F]")
    eds = tmp_path / "no-603f.eds"
    eds.write_text(text[:start] + text[text.index("\n[", start) + 1 :])
    rig = scripted([])
    with pytest.raises(ConfigError, match=r"lacks object\(s\) 0x603F:00"):
        Master(one_joint_robot, rig.network, period_s=PERIOD, eds=eds, timeouts=TIMEOUTS)
    assert rig.network.nodes == {}


def test_a_period_the_drives_cannot_take_is_a_config_error(one_joint_robot, scripted):
    rig = scripted([])
    with pytest.raises(ConfigError, match=r"SYNC period of 0\.0001234567 s"):
        Master(one_joint_robot, rig.network, period_s=0.0001234567, timeouts=TIMEOUTS)
