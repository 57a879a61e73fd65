"""Byte-exact scripts against the simulated drives, seen from a bare python-can bus: what a master
sends and what a CiA 402 drive must answer (boot-up, SDO, aborts, NMT, synchronous PDOs, the
state machine, EMCY)."""

from __future__ import annotations

import struct

import can
import pytest

from drivegain.drivers.bus import BusConfig
from drivegain.drivers.faults import FaultKind, FaultSpec
from drivegain.drivers.sim import SimConfig, SimulatedCell


class Probe:
    """A bus on the cell's channel that sends a frame and returns the next frame received."""

    def __init__(self, channel: str):
        self.bus = can.Bus(interface="virtual", channel=channel)

    def send(self, cob: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    def recv(self, timeout: float = 1.0) -> tuple[int, bytes]:
        msg = self.bus.recv(timeout)
        assert msg is not None, "no frame received"
        return msg.arbitration_id, bytes(msg.data)

    def exchange(self, cob: int, data: bytes) -> tuple[int, bytes]:
        self.send(cob, data)
        return self.recv()

    def expect(self, cob: int, request: str, answer_cob: int, answer: str) -> None:
        """Sends ``request`` (hex); the next frame must be ``answer`` (hex) on ``answer_cob``."""
        assert self.exchange(cob, h(request)) == (answer_cob, h(answer))

    def nothing(self, timeout: float = 0.05) -> bool:
        return self.bus.recv(timeout) is None


@pytest.fixture
def probe(channel):
    p = Probe(channel)
    yield p
    p.bus.shutdown()


@pytest.fixture
def cell_factory(tx40, channel):
    cells: list[SimulatedCell] = []

    def make(sim: SimConfig | None = None) -> SimulatedCell:
        cell = SimulatedCell(tx40, BusConfig("virtual", channel), sim or SimConfig(), 0.004)
        cells.append(cell)
        cell.start()
        return cell

    yield make
    for cell in cells:
        cell.stop()
        assert cell.errors == []


@pytest.fixture
def booted(probe, cell_factory):
    """Starts a cell (``booted(sim)``) and takes its six boot-up frames off the probe."""

    def start(sim: SimConfig | None = None) -> SimulatedCell:
        cell = cell_factory(sim)
        for _ in range(6):
            probe.recv()
        return cell

    return start


def h(text: str) -> bytes:
    return bytes.fromhex(text)


def test_power_on_sends_boot_up_of_every_node(probe, cell_factory):
    cell_factory()
    assert [probe.recv() for _ in range(6)] == [(0x700 + n, h("00")) for n in range(1, 7)]
    assert probe.nothing()  # no heartbeat until 0x1017 is written


SDO_ANSWERS = [
    # Device type of node 3: CiA 402 servo drive.
    (0x603, "40 00 10 00 00 00 00 00", 0x583, "43 00 10 00 92 01 02 00"),
    # Commissioned values: rated current of joint 1 (6000 mA), encoder of joint 3 (65536).
    (0x601, "40 75 60 00 00 00 00 00", 0x581, "43 75 60 00 70 17 00 00"),
    (0x603, "40 8F 60 01 00 00 00 00", 0x583, "43 8F 60 01 00 00 01 00"),
    # Mapping a valid TPDO: "not in the present device state" (0x08000022).
    (0x602, "23 00 1A 01 20 00 64 60", 0x582, "80 00 1A 01 22 00 00 08"),
    # Unsupported mode of operation 1: value range exceeded (0x06090030).
    (0x602, "2F 60 60 00 01 00 00 00", 0x582, "80 60 60 00 30 00 09 06"),
    # Writing the statusword: read-only (0x06010002).
    (0x602, "2B 41 60 00 00 00 00 00", 0x582, "80 41 60 00 02 00 01 06"),
    # Unknown object: 0x06020000.
    (0x602, "40 00 50 00 00 00 00 00", 0x582, "80 00 50 00 00 00 02 06"),
    # Mapping a non-mappable object (0x6075) into TPDO3 (disabled, empty): 0x06040041.
    (0x602, "23 02 1A 01 20 00 75 60", 0x582, "80 02 1A 01 41 00 04 06"),
]


def test_sdo_answers_and_aborts(probe, booted):
    booted()
    for cob, request, answer_cob, answer in SDO_ANSWERS:
        probe.expect(cob, request, answer_cob, answer)


def test_nmt_reset_communication_reboots_the_node_and_stopped_nodes_are_silent(probe, booted):
    booted()
    probe.send(0x000, h("82 04"))
    assert probe.recv() == (0x704, h("00"))
    probe.send(0x000, h("02 04"))  # NMT stop: no SDO any more
    probe.send(0x604, h("40 00 10 00 00 00 00 00"))
    assert probe.nothing()
    probe.send(0x000, h("80 04"))  # pre-operational: SDO again
    probe.expect(0x604, "40 00 10 00 00 00 00 00", 0x584, "43 00 10 00 92 01 02 00")


def test_state_machine_by_controlword(probe, booted):
    booted()
    sw = (0x601, h("40 41 60 00 00 00 00 00"))
    assert probe.exchange(*sw) == (0x581, h("4B 41 60 00 40 02 00 00"))  # SWITCH_ON_DISABLED
    # Enable operation straight from SWITCH_ON_DISABLED is not a transition.
    assert probe.exchange(0x601, h("2B 40 60 00 0F 00 00 00"))[1][0] == 0x60
    assert probe.exchange(*sw)[1] == h("4B 41 60 00 40 02 00 00")
    steps = [("06 00", "31 02"), ("07 00", "33 02"), ("0F 00", "37 02"), ("02 00", "17 02")]
    for cw, status in steps:  # shutdown, switch on, enable (mode 0: not following), quick stop
        probe.expect(0x601, f"2B 40 60 00 {cw} 00 00", 0x581, "60 40 60 00 00 00 00 00")
        assert probe.exchange(*sw) == (0x581, h(f"4B 41 60 00 {status} 00 00"))
    # Disable voltage ends the quick stop.
    probe.exchange(0x601, h("2B 40 60 00 00 00 00 00"))
    assert probe.exchange(*sw)[1] == h("4B 41 60 00 40 02 00 00")
    # In CSP, OPERATION_ENABLED shows "following" (bit 12).
    probe.exchange(0x601, h("2F 60 60 00 08 00 00 00"))
    probe.exchange(0x601, h("2B 40 60 00 06 00 00 00"))
    probe.exchange(0x601, h("2B 40 60 00 0F 00 00 00"))  # transitions 3 + 4 at once
    assert probe.exchange(*sw)[1] == h("4B 41 60 00 37 12 00 00")


def test_synchronous_pdos(probe, booted):
    booted()
    ok = h("60")
    # TPDO1 of node 1 (EDS default: statusword + position actual): make it synchronous.
    for frame in ("23 00 18 01 81 01 00 80", "2F 00 18 02 01 00 00 00", "23 00 18 01 81 01 00 00"):
        assert probe.exchange(0x601, h(frame))[1][:1] == ok
    # RPDO1 (EDS default: controlword): synchronous too.
    for frame in ("23 00 14 01 01 02 00 80", "2F 00 14 02 01 00 00 00", "23 00 14 01 01 02 00 00"):
        assert probe.exchange(0x601, h(frame))[1][:1] == ok
    # TPDO2: statusword + SYNC echo.
    for frame in (
        "23 01 18 01 81 02 00 80",
        "2F 01 18 02 01 00 00 00",
        "2F 01 1A 00 00 00 00 00",
        "23 01 1A 01 10 00 41 60",
        "23 01 1A 02 08 00 10 20",
        "2F 01 1A 00 02 00 00 00",
        "23 01 18 01 81 02 00 00",
    ):
        assert probe.exchange(0x601, h(frame))[1][:1] == ok
    probe.send(0x000, h("01 01"))  # NMT start node 1
    probe.send(0x080, h("05"))  # SYNC, counter 5
    assert probe.recv() == (0x181, h("40 02 00 00 00 00"))  # SWITCH_ON_DISABLED, position 0
    assert probe.recv() == (0x281, h("40 02 05"))  # echo of the SYNC counter
    # A synchronous RPDO acts at the next SYNC, not on reception.
    probe.send(0x201, h("06 00"))  # shutdown
    assert probe.exchange(0x601, h("40 41 60 00 00 00 00 00"))[1] == h("4B 41 60 00 40 02 00 00")
    probe.send(0x080, h("06"))
    # The TPDOs carry what the drive sampled at the SYNC, before it applied the RPDO.
    assert probe.recv() == (0x181, h("40 02 00 00 00 00"))
    assert probe.recv() == (0x281, h("40 02 06"))
    assert probe.exchange(0x601, h("40 41 60 00 00 00 00 00"))[1] == h("4B 41 60 00 31 02 00 00")
    probe.send(0x080, h("07"))
    assert probe.recv() == (0x181, h("31 02 00 00 00 00"))  # READY_TO_SWITCH_ON
    assert probe.recv() == (0x281, h("31 02 07"))


def test_emcy_fault_and_fault_reset(probe, booted):
    booted(SimConfig(faults=(FaultSpec(FaultKind.EMCY, node=2, at_s=0.0),)))
    probe.send(0x080, h("01"))  # the fault is due at the first SYNC
    # Following error 0x8611, error register: generic | device profile.
    assert probe.recv() == (0x082, h("11 86 21 00 00 00 00 00"))
    assert probe.exchange(0x602, h("40 41 60 00 00 00 00 00"))[1] == h("4B 41 60 00 08 02 00 00")
    assert probe.exchange(0x602, h("40 3F 60 00 00 00 00 00"))[1] == h("4B 3F 60 00 11 86 00 00")
    assert probe.exchange(0x602, h("40 01 10 00 00 00 00 00"))[1] == h("4F 01 10 00 21 00 00 00")
    # Bit 7 already low: one write with it set is a rising edge; EMCY "error reset" follows.
    probe.send(0x602, h("2B 40 60 00 80 00 00 00"))
    assert probe.recv() == (0x082, h("00 00 00 00 00 00 00 00"))
    assert probe.recv() == (0x582, h("60 40 60 00 00 00 00 00"))
    assert probe.exchange(0x602, h("40 41 60 00 00 00 00 00"))[1] == h("4B 41 60 00 40 02 00 00")
    # The error history 0x1003 keeps the code.
    assert probe.exchange(0x602, h("40 03 10 01 00 00 00 00"))[1] == h("43 03 10 01 11 86 00 00")


def test_heartbeat_consumer_time_out_sends_emcy_8130_and_faults(probe, booted):
    """0x1016 sub 1 = producer 127 (the master) << 16 | 6 ms: monitoring starts with its first
    heartbeat; in lockstep each SYNC is 4 ms of simulated time, so the second SYNC after the last
    heartbeat passes the time-out."""
    booted()
    probe.expect(0x602, "23 16 10 01 06 00 7F 00", 0x582, "60 16 10 01 00 00 00 00")
    probe.send(0x080, h("01"))
    assert probe.nothing()  # not monitoring before the producer's first heartbeat
    probe.send(0x77F, h("05"))  # the master's heartbeat: NMT operational
    probe.send(0x080, h("02"))
    assert probe.nothing()
    probe.send(0x080, h("03"))
    # Heartbeat error 0x8130, error register: generic | communication.
    assert probe.recv() == (0x082, h("30 81 11 00 00 00 00 00"))
    assert probe.exchange(0x602, h("40 41 60 00 00 00 00 00"))[1] == h("4B 41 60 00 08 02 00 00")
    assert probe.exchange(0x602, h("40 3F 60 00 00 00 00 00"))[1] == h("4B 3F 60 00 30 81 00 00")
    assert probe.nothing()  # only the node that watches


def test_tpdo_layout_matches_struct_sizes():
    # The TPDO layouts the master maps must fit the 8 bytes of a CAN frame.
    from drivegain.drivers.objects import PLAIN_LAYOUT, TAGGED_LAYOUT, pdo_struct

    for layout in (TAGGED_LAYOUT, PLAIN_LAYOUT):
        for entries in (layout.rpdo, *layout.tpdos):
            assert pdo_struct(entries).size <= 8
    assert struct.calcsize("<ihBB") == pdo_struct(TAGGED_LAYOUT.tpdo1).size == 8
