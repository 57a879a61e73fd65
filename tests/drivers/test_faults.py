"""Every fault the simulator can inject is detected by the master within its time limit, with the
node id and the code in the error.

The rig runs in lockstep: every time limit counts the simulated clock the master shares with the
drives (drivers/simtime.py), so the detection instants asserted here are exact in simulated time,
the same on a quiet and on a saturated machine. Wall-clock bounds only guard against a hang.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivegain.drivers.cia402 import State
from drivegain.drivers.faults import FaultKind, FaultSpec
from drivegain.drivers.master import Timeouts
from drivegain.drivers.sim import SimConfig
from drivegain.errors import BusError, DriveError
from drivegain.formats.log import EventLevel

PERIOD = 0.004
AT_S = 0.2  # simulated time of the fault
AT_CYCLE = round(AT_S / PERIOD)  # the SYNC that triggers it
TIMEOUTS = Timeouts(boot_s=0.4, sdo_s=0.3, state_s=0.3, heartbeat_s=0.3, tpdo_s=0.1)
#: Simulated-time rounding allowed on an instant (the clock stands on the simulation step).
EXACT = 1e-6
#: Wall-clock bound of a test that waits for a free-running clock (against a hang only).
HANG_GUARD_S = 30.0


def stream_until_error(rig, max_cycles: int = 5000) -> tuple[DriveError, int, float]:
    """Boot, enable, cycle at the current position until the master raises.

    Returns the error, the index of the failing cycle and when it was raised on the drives'
    clock (simulated time in lockstep)."""
    master = rig.master
    master.boot()
    master.enable()
    q = master.read_positions()
    for k in range(max_cycles):
        try:
            master.cycle(q)
        except DriveError as exc:
            return exc, k, rig.cell.clock.now()
    raise AssertionError("no fault detected")


def fault_time(rig) -> float:
    (record,) = rig.cell.fault_log()
    assert record.sim_time_s == pytest.approx(AT_S, abs=PERIOD)
    return record.clock_s


@pytest.mark.parametrize(
    ("kind", "code", "expected_state"),
    [(FaultKind.EMCY, 0x8611, State.FAULT), (FaultKind.FAULT, 0x2310, State.FAULT)],
)
def test_drive_fault_is_reported_in_the_cycle_it_happens(
    tx40, channel, rig_factory, kind, code, expected_state
):
    sim = SimConfig(faults=(FaultSpec(kind, node=3, at_s=AT_S),))
    with rig_factory(tx40, channel, sim, PERIOD, TIMEOUTS) as rig:
        err, cycle, _ = stream_until_error(rig)
        assert (err.node, err.code) == (3, code)
        assert err.state is expected_state
        assert cycle == AT_CYCLE
        # On the way down: the others quick stop, then a fault reset brings everything back.
        rig.master.quick_stop()
        assert all(s != State.OPERATION_ENABLED for s in rig.master.states.values())
        rig.master.enable()
        q = rig.master.read_positions()
        for _ in range(10):
            rig.master.cycle(q)
        events = rig.master.drain_events()
        assert rig.cell.errors == []
    if kind == FaultKind.EMCY:
        assert any(e.code == code and e.node == 3 and e.level is EventLevel.ERROR for e in events)
        assert any(e.code == 0 and e.node == 3 for e in events)  # EMCY error reset


def test_heartbeat_stop_is_detected_within_the_consumer_time(tx40, channel, rig_factory):
    sim = SimConfig(faults=(FaultSpec(FaultKind.HEARTBEAT_STOP, node=5, at_s=AT_S),))
    with rig_factory(tx40, channel, sim, PERIOD, TIMEOUTS) as rig:
        err, _, raised = stream_until_error(rig)
        stopped = fault_time(rig)
    assert (err.node, err.code) == (5, 0x8130)
    # The last heartbeat left at most one producer period before the stop; the consumer is
    # checked once per cycle.
    delay = raised - stopped
    limit = TIMEOUTS.heartbeat_s
    assert limit - TIMEOUTS.heartbeat_producer_s - EXACT <= delay <= limit + PERIOD + EXACT


@pytest.mark.parametrize(
    "spec",
    [
        FaultSpec(FaultKind.TPDO_MISSING, node=6, at_s=AT_S, tpdo=2),
        FaultSpec(FaultKind.TPDO_LATE, node=2, at_s=AT_S, delay_s=0.3),
    ],
    ids=["missing", "late"],
)
def test_missing_or_late_tpdo_is_detected_after_the_tpdo_time(tx40, channel, rig_factory, spec):
    with rig_factory(tx40, channel, SimConfig(faults=(spec,)), PERIOD, TIMEOUTS) as rig:
        err, cycle, raised = stream_until_error(rig)
        started = fault_time(rig)
    assert (err.node, err.code) == (spec.node, 0x8250)
    assert cycle == AT_CYCLE
    assert raised - started == pytest.approx(TIMEOUTS.tpdo_s, abs=EXACT)


def test_a_late_tpdo_within_the_limit_is_tagged_to_its_own_sync(tx40, channel, rig_factory):
    spec = FaultSpec(FaultKind.TPDO_LATE, node=4, at_s=0.0, delay_s=0.02, tpdo=1)
    with rig_factory(tx40, channel, SimConfig(faults=(spec,)), PERIOD, TIMEOUTS) as rig:
        rig.master.boot()
        rig.master.enable()
        q = rig.master.read_positions()
        samples = [rig.master.cycle(q) for _ in range(10)]
        history = rig.cell.joint_torque_history()
    # in lockstep the delay is simulated time: exactly the fault's
    assert all(s.latency_s == pytest.approx(0.02, abs=EXACT) for s in samples)
    counters = np.array([s.raw["sync_counter"] for s in samples])
    assert np.all(counters == history.counter[:, None])


def test_a_node_that_never_boots_fails_the_boot(tx40, channel, rig_factory):
    sim = SimConfig(faults=(FaultSpec(FaultKind.NEVER_BOOTS, node=4),))
    with rig_factory(tx40, channel, sim, PERIOD, TIMEOUTS) as rig:
        start = rig.cell.clock.now()
        wall = time.monotonic()
        with pytest.raises(DriveError) as info:
            rig.master.boot()
        elapsed = rig.cell.clock.now() - start
        assert time.monotonic() - wall < HANG_GUARD_S
    assert (info.value.node, info.value.code) == (4, 0x8130)
    assert elapsed == pytest.approx(TIMEOUTS.boot_s, abs=EXACT)


def test_bus_off_is_a_bus_error(tx40, channel, rig_factory):
    sim = SimConfig(faults=(FaultSpec(FaultKind.BUS_ERROR, at_s=AT_S),))
    with rig_factory(tx40, channel, sim, PERIOD, TIMEOUTS) as rig:
        err, cycle, raised = stream_until_error(rig)
        happened = fault_time(rig)
    assert isinstance(err, BusError)
    assert (err.node, err.code) == (None, 0x8140)
    assert cycle == AT_CYCLE  # the error frame goes out before the TPDOs of its SYNC
    assert raised - happened <= EXACT


def test_following_error_of_the_drive_itself(tx40, channel, rig_factory):
    # A target jump far beyond the following error window (0.1 rad) faults the drive: 0x8611.
    with rig_factory(tx40, channel, SimConfig(), PERIOD, TIMEOUTS) as rig:
        rig.master.boot()
        rig.master.enable()
        q = rig.master.read_positions()
        rig.master.cycle(q)
        jump = q.copy()
        jump[0] += 0.5
        with pytest.raises(DriveError) as info:
            for _ in range(50):
                rig.master.cycle(jump)
        assert rig.cell.errors == []
    assert (info.value.node, info.value.code) == (1, 0x8611)


def test_power_loss_of_every_drive_is_noticed_and_close_does_not_hang(tx40, channel, rig_factory):
    """With the drives gone nothing advances the simulated clock any more: it follows the wall
    clock from there, so the master's consumer still notices the silence."""
    with rig_factory(tx40, channel, SimConfig(), PERIOD, TIMEOUTS) as rig:
        rig.master.boot()
        rig.master.enable()
        rig.master.drain_events()
        rig.cell.stop()  # the drives lose power: no heartbeat, no SDO, no PDO
        deadline = time.monotonic() + HANG_GUARD_S
        with pytest.raises(DriveError) as info:
            while time.monotonic() < deadline:
                rig.master.check()
                time.sleep(0.01)
        rig.master.close()  # skips the silent drives instead of waiting for SDO time-outs
        events = rig.master.drain_events()
    assert info.value.code == 0x8130 and info.value.node in tx40.node_ids
    skipped = {e.node for e in events if "no heartbeat: drive skipped" in e.text}
    # heartbeat phases differ per drive: when the first is noticed lost, another may still be
    # within its consumer time and get one SDO attempt, never more than one
    assert len(skipped) >= tx40.n - 1
