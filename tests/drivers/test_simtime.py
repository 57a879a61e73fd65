"""The lockstep clock on its own: waits count simulated time, actions run in time order, nothing
in flight blocks a jump, a real hang is a clear error, and a side that leaves hands the clock to
the wall."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import can
import pytest

from drivegain.drivers.simtime import LockstepClock
from drivegain.errors import DriveError


def fake_network() -> SimpleNamespace:
    """What :meth:`LockstepClock.attach` uses of a canopen network: its bus and notifier."""
    listeners: list[can.Listener] = []
    bus = SimpleNamespace(
        sent=[], preserve_timestamps=False, shutdown=lambda: None, listeners=listeners
    )
    bus.send = lambda msg, timeout=None: bus.sent.append(msg)
    notifier = SimpleNamespace(add_listener=listeners.append)
    return SimpleNamespace(bus=bus, notifier=notifier)


def test_a_wait_with_nothing_in_flight_jumps_through_the_actions_to_its_deadline():
    clock = LockstepClock()
    fired: list[tuple[str, float]] = []
    clock.call_at(0.3, lambda: fired.append(("b", clock.now())))
    clock.call_at(0.1, lambda: fired.append(("a", clock.now())))
    clock.call_at(5.0, lambda: fired.append(("late", clock.now())))
    wall = time.monotonic()
    assert clock.wait(threading.Event(), 1.0, "nothing") is False
    assert time.monotonic() - wall < 1.0  # simulated time, not wall time
    assert fired == [("a", 0.1), ("b", 0.3)]
    assert clock.now() == pytest.approx(1.0)


def test_an_action_that_sets_the_flag_ends_the_wait_at_its_instant():
    clock = LockstepClock()
    flag = threading.Event()
    clock.call_at(0.25, flag.set)
    assert clock.wait(flag, 1.0, "the flag") is True
    assert clock.now() == pytest.approx(0.25)


def test_sync_instants_are_one_period_apart_on_the_step():
    clock = LockstepClock()
    assert [clock.sync_instant(0.004, 0.0005) for _ in range(3)] == pytest.approx(
        [0.004, 0.008, 0.012]
    )


def test_a_frame_in_flight_that_never_arrives_is_a_hang_naming_what_waited():
    clock = LockstepClock(hang_s=0.2)
    master, drives = fake_network(), fake_network()
    clock.attach(master, "master")
    clock.attach(drives, "drives")
    master.bus.send(can.Message(arbitration_id=0x80, data=b"\x01"))  # never handled
    assert master.bus.sent[0].timestamp == 0.0  # stamped with simulated time
    with pytest.raises(DriveError, match="hung: waiting for the TPDOs of cycle 7"):
        clock.wait(threading.Event(), 1.0, "the TPDOs of cycle 7")
    assert clock.now() == 0.0  # no jump while something was in flight
    drives.bus.listeners[-1].on_message_received(master.bus.sent[0])  # handled at last
    assert clock.settled()


def test_when_a_side_leaves_the_clock_follows_the_wall_and_runs_the_others_actions():
    clock = LockstepClock()
    master, drives = fake_network(), fake_network()
    clock.attach(master, "master")
    clock.attach(drives, "drives")
    fired = threading.Event()
    clock.call_at(0.05, fired.set)
    clock.detach("master")
    assert clock.free_running
    assert fired.wait(5.0)  # from the clock's own thread, about 0.05 s of wall time later
    before = clock.now()
    time.sleep(0.02)
    assert clock.now() > before
    clock.close()
