"""Lockstep on the in-process virtual bus: a frame between the master's and the drives' networks
is handled by the receiver's listeners in the sender's thread, before the send returns, in the
order sent (no reader thread, no hand-off); a receiver may send in turn, even on the sender's
network; a bus of the channel that is no party of the clock (a trace) still gets every frame."""

from __future__ import annotations

import threading
import time

import can
import pytest

from drivegain.drivers.bus import BusConfig, open_network
from drivegain.drivers.simtime import LockstepClock


@pytest.fixture
def pair():
    """A lockstep clock with two attached networks on a fresh virtual channel, and the channel."""
    cfg = BusConfig("virtual", f"delivery-{time.monotonic_ns()}")
    master, drives = open_network(cfg), open_network(cfg)
    clock = LockstepClock(hang_s=5.0)
    clock.attach(drives, "drives")
    clock.attach(master, "master")
    try:
        yield clock, master, drives, cfg
    finally:
        master.disconnect()
        drives.disconnect()
        clock.close()


def test_a_frame_is_handled_in_the_senders_thread_before_the_send_returns(pair):
    clock, master, drives, _ = pair
    seen: list[tuple[int, bytes, float, int]] = []
    drives.subscribe(
        0x201, lambda cob, data, t: seen.append((cob, bytes(data), t, threading.get_ident()))
    )
    clock.advance_to(0.25)
    master.send_message(0x201, b"\x01\x02")
    assert seen == [(0x201, b"\x01\x02", 0.25, threading.get_ident())]
    assert clock.settled()


def test_a_receiver_sends_back_on_the_senders_network_in_order_without_deadlock(pair):
    """As a SYNC handled by the drives advances the clock and fires the master's heartbeat: the
    send lock of the master's network is not re-entrant, delivery waits for its release."""
    clock, master, drives, _ = pair
    order: list[str] = []

    def on_sync(cob: int, data: bytearray, t: float) -> None:
        order.append("sync")
        master.send_message(0x77F, b"\x05")  # the master's heartbeat, from the drives' handler
        drives.send_message(0x181, b"\x00")  # the answer
        order.append("sync handled")

    drives.subscribe(0x80, on_sync)
    drives.subscribe(0x77F, lambda *_: order.append("heartbeat"))
    master.subscribe(0x181, lambda *_: order.append("tpdo"))
    done = threading.Event()
    thread = threading.Thread(target=lambda: (master.send_message(0x80, b"\x01"), done.set()))
    thread.start()
    thread.join(5.0)
    assert done.is_set(), "sending a SYNC deadlocked"
    assert order == ["sync", "sync handled", "heartbeat", "tpdo"]
    assert clock.settled()


def test_a_bus_that_is_no_party_still_gets_every_frame(pair):
    _, master, drives, cfg = pair
    with can.Bus(interface="virtual", channel=cfg.channel) as trace:
        drives.subscribe(0x80, lambda *_: drives.send_message(0x181, b"\x07"))
        master.send_message(0x80, b"\x01")
        got = [trace.recv(1.0), trace.recv(1.0)]
    assert [(m.arbitration_id, bytes(m.data)) for m in got if m is not None] == [
        (0x80, b"\x01"),
        (0x181, b"\x07"),
    ]


def test_after_a_side_left_its_frames_take_the_bus_reader_again(pair):
    clock, master, drives, _ = pair
    got = threading.Event()
    threads: list[int] = []

    def on_frame(*_: object) -> None:
        threads.append(threading.get_ident())
        got.set()

    master.subscribe(0x701, on_frame)
    clock.detach("master")
    drives.send_message(0x701, b"\x05")
    assert got.wait(2.0)
    assert threads != [threading.get_ident()]  # master's reader thread, not this one
