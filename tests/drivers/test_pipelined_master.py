"""The pipelined cycle (realtime): SYNC k goes out, then the TPDOs of cycle k−1 are taken.

Byte-exact scripts as in test_master_script.py (whose boot and enable scripts are reused): a
scripted drive answers each SYNC only after the master's next SYNC, later than the period. The
pipelined master still loses no cycle and files every answer under its own SYNC, with the target
sent in it; a drive that stops answering is reported by the call that sends the next SYNC.
Nothing here measures time: what is checked is which frames went out and what came back.
"""

from __future__ import annotations

import importlib.util
import math
import struct
from pathlib import Path
from types import ModuleType

import pytest

from drivegain.drivers import objects as ob
from drivegain.drivers.master import Master, Timeouts
from drivegain.errors import DriveError, UsageError

NODE = 1
PERIOD = 0.004
#: short TPDO time-out: the missing-TPDO test waits for it once
TIMEOUTS = Timeouts(boot_s=0.5, sdo_s=0.2, state_s=0.05, heartbeat_s=5.0, tpdo_s=0.05)
#: encoder counts per joint radian of the one-joint robot (32:1 gear, 196608 counts/rev)
COUNTS_PER_RAD = 32 * 196608 / (2 * math.pi)


def _scripts() -> ModuleType:
    """The boot, enable and close scripts of test_master_script.py (tests are not a package)."""
    path = Path(__file__).with_name("test_master_script.py")
    spec = importlib.util.spec_from_file_location("_master_scripts", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


S = _scripts()


def rpdo(f, counts: int, cw: int = 0x000F) -> tuple:
    return (f.TX, 0x201, struct.pack("<iH", counts, cw))


def sync(f, counter: int) -> tuple:
    return (f.TX, 0x080, bytes([counter]))


def tpdo1(f, counter: int, position: int) -> tuple:
    return (f.RX, 0x181, struct.pack("<ihBB", position, 10 * counter, counter, 0))


def tpdo2(f, counter: int, sw: int = 0x1237) -> tuple:
    return (f.RX, 0x281, struct.pack("<HhhBb", sw, 20 * counter, 20 * counter, counter, 8))


def disable_and_close(f) -> list[tuple]:
    """close() of an enabled drive: shutdown, the state checked, then the close script."""
    return [
        *f.sdo_write(NODE, 0x6040, 0, f.u16(0x0006)),
        *f.sdo_read(NODE, 0x6041, 0, f.u16(0x0231)),
        *S.close_script(f),
    ]


def targets(cycles: int) -> list[float]:
    """A different target for every cycle, rad."""
    return [0.001 * (k + 1) for k in range(cycles)]


def counts_of(q: float) -> int:
    return round(q * COUNTS_PER_RAD)


def test_answers_after_the_next_sync_are_filed_under_their_own(one_joint_robot, scripted, frames):
    """Each SYNC is answered only after the next one went out (TPDO2 of SYNC 3 even after SYNC
    4): a same-cycle master would time out at once; the pipelined one returns every cycle, one
    call later, with the values and target of its own SYNC. A TPDO of a long-gone SYNC is
    dropped with a warning."""
    f = frames
    q = targets(4)
    c = [counts_of(x) for x in q]
    script = [
        *S.boot_script(f),
        *S.enable_script(f),
        rpdo(f, c[0]),
        sync(f, 1),  # no answer before the next SYNC
        rpdo(f, c[1]),
        sync(f, 2),
        tpdo1(f, 1, 5001),
        tpdo2(f, 1),
        rpdo(f, c[2]),
        sync(f, 3),
        tpdo1(f, 2, 5002),
        tpdo1(f, 200, 9999),  # an answer to a SYNC long past
        tpdo2(f, 2),
        tpdo1(f, 3, 5003),  # half of SYNC 3's answers before SYNC 4...
        rpdo(f, c[3]),
        sync(f, 4),
        tpdo2(f, 3),  # ...the other half after it
        tpdo1(f, 4, 5004),
        tpdo2(f, 4),
        *disable_and_close(f),
    ]
    rig = scripted(script)
    master = Master(one_joint_robot, rig.network, period_s=PERIOD, timeouts=TIMEOUTS)
    assert master.layout.tagged
    master.boot()
    master.enable()
    master.drain_events()
    steps = [master.cycle_pipelined([x]) for x in q]
    last = master.collect_pending()
    assert master.collect_pending() is None  # nothing left in flight
    events = [e.text for e in master.drain_events()]
    master.close()
    assert rig.bus.mismatches == [] and rig.bus.remaining() == []

    assert [s.sent.cycle for s in steps] == [0, 1, 2, 3]
    assert steps[0].sample is None
    samples = [s.sample for s in steps[1:]] + [last]
    assert all(s is not None for s in samples)
    for k, s in enumerate(samples):
        assert s is not None
        assert s.cycle == k
        assert s.raw["sync_counter"] == [ob.sync_counter(k)] == [k + 1]
        assert s.raw["position"] == [5001 + k]
        assert s.raw["target"] == [c[k]]  # the target sent with this SYNC, not a later one
        assert s.position[0] == pytest.approx((5001 + k) / COUNTS_PER_RAD, rel=1e-12)
        assert s.current[0] == pytest.approx(20 * (k + 1) / 1000 * 6.0)
        # the sample carries its own SYNC's times, the step those of the SYNC it just sent
        assert s.sync_time_ns == steps[k].sent.sync_time_ns
        assert s.sync_monotonic_s == steps[k].sent.sync_monotonic_s
    assert master.stale_frames == 1
    assert any("TPDO1 of SYNC 200 arrived during SYNC" in t for t in events)


def test_a_drive_that_stops_answering_is_reported_by_the_next_sync(
    one_joint_robot, scripted, frames
):
    """Cycle 1 (SYNC 2) is never answered: the call that sends SYNC 3 raises the missing TPDO of
    cycle 1, and no SYNC 4 goes out. The quick stop then drops the cycle in flight: a late answer
    to SYNC 3 is ignored without an event, and the drive is brought to rest."""
    f = frames
    q = targets(3)
    c = [counts_of(x) for x in q]
    script = [
        *S.boot_script(f),
        *S.enable_script(f),
        rpdo(f, c[0]),
        sync(f, 1),
        rpdo(f, c[1]),
        sync(f, 2),
        tpdo1(f, 1, 5001),
        tpdo2(f, 1),  # SYNC 2 is never answered
        rpdo(f, c[2]),
        sync(f, 3),
        # quick stop: controlword by SDO, then SYNCs with quick stop until the drive rests
        *f.sdo_write(NODE, 0x6040, 0, f.u16(0x0002)),
        rpdo(f, c[2], 0x0002),
        sync(f, 4),
        tpdo1(f, 3, 5003),  # the answer to the abandoned SYNC 3
        tpdo2(f, 3),
        tpdo1(f, 4, 5004),
        tpdo2(f, 4, sw=0x0240),  # at rest: SWITCH_ON_DISABLED
        *S.close_script(f),
    ]
    rig = scripted(script)
    master = Master(one_joint_robot, rig.network, period_s=PERIOD, timeouts=TIMEOUTS)
    master.boot()
    master.enable()
    master.drain_events()
    first = master.cycle_pipelined([q[0]])
    second = master.cycle_pipelined([q[1]])
    assert first.sample is None and second.sample is not None and second.sample.cycle == 0
    with pytest.raises(DriveError) as err:
        master.cycle_pipelined([q[2]])
    assert (err.value.node, err.value.code) == (NODE, 0x8250)
    assert "TPDO1 of cycle 1 missing" in str(err.value)
    # raised by the call that sent SYNC 3: one SYNC after the silent one, not two
    assert [data for cob, data in rig.bus.sent if cob == 0x080] == [b"\x01", b"\x02", b"\x03"]
    master.quick_stop()
    events = [e.text for e in master.drain_events()]
    master.close()
    assert rig.bus.mismatches == [] and rig.bus.remaining() == []
    assert not any("arrived during SYNC" in t for t in events)
    assert master.stale_frames == 2  # SYNC 3's two TPDOs


def test_without_the_sync_echo_a_cycle_closes_before_the_next_sync(
    one_joint_robot, scripted, frames, tmp_path
):
    """Drives without the echo (0x2010): a cycle's TPDOs are those received before the next
    SYNC, so the pipelined master takes them before sending it. Answered in time, every cycle
    comes back one call later; an answer that has not come by then is missing, and the next SYNC
    is not sent (it would make the late answer look like its own)."""
    f = frames
    eds = S.no_echo_eds(tmp_path)
    plain1, plain2 = S.NO_ECHO_TPDOS
    q = targets(3)
    c = [counts_of(x) for x in q]

    def answer(position: int) -> list[tuple]:
        return [
            (f.RX, 0x181, struct.pack("<ihH", position, -50, 0x1237)),
            (f.RX, 0x281, struct.pack("<hhBb", -52, -52, 0, 8)),
        ]

    script = [
        *S.boot_script(f, plain1, plain2),
        *S.enable_script(f),
        rpdo(f, c[0]),
        sync(f, 1),
        *answer(7001),
        rpdo(f, c[1]),
        sync(f, 2),
        *answer(7002),
        rpdo(f, c[2]),
        sync(f, 3),  # never answered
        *disable_and_close(f),
    ]
    rig = scripted(script)
    master = Master(one_joint_robot, rig.network, period_s=PERIOD, eds=eds, timeouts=TIMEOUTS)
    assert not master.layout.tagged
    master.boot()
    master.enable()
    steps = [master.cycle_pipelined([x]) for x in q]
    got = [s.sample for s in steps]
    assert got[0] is None
    assert [(s.cycle, s.raw["position"], s.raw["target"]) for s in got[1:] if s] == [
        (0, [7001], [c[0]]),
        (1, [7002], [c[1]]),
    ]
    with pytest.raises(DriveError) as err:
        master.cycle_pipelined([q[2]])
    assert (err.value.node, err.value.code) == (NODE, 0x8250)
    assert "of cycle 2 missing" in str(err.value)
    master.close()
    assert rig.bus.mismatches == [] and rig.bus.remaining() == []
    # no SYNC 4: the silent cycle was closed before the next SYNC could go out
    assert [data for cob, data in rig.bus.sent if cob == 0x080] == [b"\x01", b"\x02", b"\x03"]


def test_staged_rpdos_go_out_ahead_and_the_sync_alone_at_the_deadline(
    one_joint_robot, scripted, frames
):
    """stage() sends a cycle's RPDO at once and no SYNC; cycle_pipelined() with the same target
    then sends the SYNC alone, and the samples are those of the unstaged cycle. A target other
    than the staged one is refused before any SYNC; the disable forgets what was staged."""
    f = frames
    q = targets(3)
    c = [counts_of(x) for x in q]
    script = [*S.boot_script(f), *S.enable_script(f)]
    for k in range(3):
        script += [rpdo(f, c[k]), sync(f, k + 1), tpdo1(f, k + 1, 5001 + k), tpdo2(f, k + 1)]
    script += [rpdo(f, counts_of(0.5)), *disable_and_close(f)]
    rig = scripted(script)
    master = Master(one_joint_robot, rig.network, period_s=PERIOD, timeouts=TIMEOUTS)
    master.boot()
    master.enable()
    samples = []
    for x in q:
        before = len(rig.bus.sent)
        master.stage([x])
        assert [cob for cob, _ in rig.bus.sent[before:]] == [0x201]  # the RPDO, no SYNC yet
        step = master.cycle_pipelined([x])
        assert [cob for cob, _ in rig.bus.sent[before + 1 :]] == [0x080]  # the SYNC alone
        samples.append(step.sample)
    samples = [*samples[1:], master.collect_pending()]
    assert [s.raw["target"] for s in samples] == [[x] for x in c]
    assert [s.raw["position"] for s in samples] == [[5001], [5002], [5003]]
    master.stage([0.5])
    with pytest.raises(UsageError, match="not the target staged"):
        master.cycle_pipelined([0.6])
    master.close()
    assert rig.bus.mismatches == [] and rig.bus.remaining() == []
    assert [data for cob, data in rig.bus.sent if cob == 0x080] == [b"\x01", b"\x02", b"\x03"]
