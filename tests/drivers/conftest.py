"""Fixtures of the drivers tests: robots, unique virtual channels, a scripted CAN bus, and a
master + simulated cell pair on the virtual bus."""

from __future__ import annotations

import contextlib
import itertools
import queue
import struct
import textwrap
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import can
import canopen
import pytest

from drivegain.config import Robot, load_robot, resource_path
from drivegain.drivers.bus import BusConfig, open_network
from drivegain.drivers.master import Master, Timeouts
from drivegain.drivers.realtime import RealtimePolicy
from drivegain.drivers.sim import SimConfig, SimulatedCell

TX, RX, TX_REPEAT = "tx", "rx", "tx*"
_channel_ids = itertools.count()


@pytest.fixture(scope="session")
def tx40() -> Robot:
    return load_robot(resource_path("tx40.toml"))


@pytest.fixture
def one_joint_robot(tmp_path: Path) -> Robot:
    """A single TX-40-like joint on node 1 (32:1 gear, 196608 counts/rev, 6 A)."""
    p = tmp_path / "one.toml"
    p.write_text(
        textwrap.dedent(
            """
            [robot]
            name = "one joint"
            [[joint]]
            name = "j1"
            mdh = { sigma = 0, alpha = 0.0, d = 0.0, theta_offset = 0.0, r = 0.0 }
            position_limits = [-3.0, 3.0]
            velocity_limit = 5.0
            acceleration_limit = 12.0
            jerk_limit = 80.0
            gear_ratio = 32.0
            encoder_counts = 196608
            rated_current = 6.0
            node_id = 1
            apriori_gain = 32.96
            """
        )
    )
    return load_robot(p)


@pytest.fixture
def channel(request: pytest.FixtureRequest) -> str:
    """A virtual CAN channel name no other test uses."""
    return f"dg-{request.node.name}-{next(_channel_ids)}"


# --- expected frames (CiA 301), written independently of the code under test ------------------
def sdo_write(node: int, index: int, sub: int, data: bytes) -> list[tuple[str, int, bytes]]:
    """Expedited SDO download request and its confirmation."""
    n = len(data)
    head = bytes([0x23 | (4 - n) << 2, index & 0xFF, index >> 8, sub])
    return [
        (TX, 0x600 + node, head + data + bytes(4 - n)),
        (RX, 0x580 + node, bytes([0x60, index & 0xFF, index >> 8, sub, 0, 0, 0, 0])),
    ]


def sdo_read(node: int, index: int, sub: int, data: bytes) -> list[tuple[str, int, bytes]]:
    """SDO upload request and its expedited response carrying ``data``."""
    n = len(data)
    return [
        (TX, 0x600 + node, bytes([0x40, index & 0xFF, index >> 8, sub, 0, 0, 0, 0])),
        (
            RX,
            0x580 + node,
            bytes([0x43 | (4 - n) << 2, index & 0xFF, index >> 8, sub]) + data + bytes(4 - n),
        ),
    ]


def u8(v: int) -> bytes:
    return struct.pack("<B", v)


def i8(v: int) -> bytes:
    return struct.pack("<b", v)


def u16(v: int) -> bytes:
    return struct.pack("<H", v)


def u32(v: int) -> bytes:
    return struct.pack("<I", v)


def i32(v: int) -> bytes:
    return struct.pack("<i", v)


#: The master's heartbeat with the default node id 127: NMT operational (CiA 301).
MASTER_HEARTBEAT = (0x77F, bytes([0x05]))


class ScriptedBus(can.BusABC):
    """A CAN bus that plays a script: every frame sent must be the next ``tx`` entry, byte for
    byte; the ``rx`` entries that follow are then received. A ``tx*`` entry (cob, data,
    response) may match any number of times until the next entry matches.

    ``background`` frames (cob -> data) are periodic frames of their own thread (the master's
    heartbeat): they may come between any two entries, must match byte for byte, and are kept in
    :attr:`background_sent` instead of playing the script."""

    def __init__(self, script: list[tuple], background: dict[int, bytes] | None = None):
        self.script: deque[tuple] = deque(script)
        self.background = dict(background or {})
        self.background_sent: list[tuple[float, int, bytes]] = []
        self.sent: list[tuple[int, bytes]] = []
        self.mismatches: list[str] = []
        self._rx: queue.Queue[can.Message] = queue.Queue()
        super().__init__(channel="scripted")
        self._deliver()

    def _deliver(self) -> None:
        while self.script and self.script[0][0] == RX:
            _, cob, data = self.script.popleft()
            self._rx.put(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    def _matches(self, entry: tuple, cob: int, data: bytes) -> bool:
        return entry[1] == cob and entry[2] == data

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        cob, data = msg.arbitration_id, bytes(msg.data)
        if cob in self.background:
            if data != self.background[cob]:
                self.mismatches.append(f"background {cob:03X} {data.hex(' ')}")
            self.background_sent.append((time.monotonic(), cob, data))
            return
        self.sent.append((cob, data))
        while self.script and self.script[0][0] == TX_REPEAT:
            entry = self.script[0]
            if self._matches(entry, cob, data):
                _, _, _, response = entry
                self._rx.put(
                    can.Message(arbitration_id=response[0], data=response[1], is_extended_id=False)
                )
                return
            self.script.popleft()
        expected = self.script.popleft() if self.script else None
        if expected is None or expected[0] != TX or not self._matches(expected, cob, data):
            want = "nothing" if expected is None else f"{expected[1]:03X} {expected[2].hex(' ')}"
            text = f"sent {cob:03X} {data.hex(' ')}, script expected {want}"
            self.mismatches.append(text)
            raise can.CanOperationError(text)
        self._deliver()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            return self._rx.get(timeout=timeout), False
        except queue.Empty:
            return None, False

    def remaining(self) -> list[tuple]:
        """Script entries not played (``tx*`` entries may remain)."""
        return [e for e in self.script if e[0] != TX_REPEAT]


@dataclass
class Scripted:
    bus: ScriptedBus
    network: canopen.Network


@pytest.fixture
def scripted() -> Iterator[Callable[[list[tuple]], Scripted]]:
    """Factory: a connected canopen Network on a ScriptedBus (disconnected after the test)."""
    made: list[canopen.Network] = []

    def make(script: list[tuple], background: dict[int, bytes] | None = None) -> Scripted:
        bus = ScriptedBus(script, dict([MASTER_HEARTBEAT]) if background is None else background)
        network = canopen.Network(bus)
        network.NOTIFIER_CYCLE = 0.02
        network.connect()
        made.append(network)
        return Scripted(bus, network)

    yield make
    for network in made:
        network.disconnect()


#: Timeouts for tests: short where a test waits for them, generous for the heartbeat so that a
#: loaded machine does not make a test flaky.
FAST = Timeouts(boot_s=1.0, sdo_s=0.3, state_s=0.3, heartbeat_s=1.0, tpdo_s=0.2, quick_stop_s=2.0)


@dataclass
class Rig:
    cell: SimulatedCell
    master: Master
    network: canopen.Network
    bus_cfg: BusConfig


@contextlib.contextmanager
def make_rig(
    robot: Robot,
    channel: str,
    sim: SimConfig | None = None,
    period_s: float = 0.004,
    timeouts: Timeouts = FAST,
) -> Iterator[Rig]:
    """A simulated cell and a master on one virtual channel; everything closed on exit.

    As the acquisition rig does: the realtime policy's process part (garbage-collector freeze)
    is held from before the drives start to after they stop, and in lockstep the master shares
    the drives' simulated clock.
    """
    bus_cfg = BusConfig("virtual", channel)
    with RealtimePolicy().process():
        cell = SimulatedCell(robot, bus_cfg, sim or SimConfig(), period_s)
        cell.start()
        try:
            network = open_network(bus_cfg)
            try:
                master = Master(
                    robot,
                    network,
                    period_s=period_s,
                    timeouts=timeouts,
                    clock=cell.clock.lockstep,
                )
                try:
                    yield Rig(cell, master, network, bus_cfg)
                finally:
                    master.close()
            finally:
                network.disconnect()
        finally:
            cell.stop()


@pytest.fixture
def rig_factory():
    return make_rig


@pytest.fixture
def frames() -> SimpleNamespace:
    """CiA 301 frame builders for scripts (tests cannot import conftest in importlib mode)."""
    return SimpleNamespace(
        TX=TX,
        RX=RX,
        TX_REPEAT=TX_REPEAT,
        sdo_write=sdo_write,
        sdo_read=sdo_read,
        u8=u8,
        i8=i8,
        u16=u16,
        u32=u32,
        i32=i32,
    )


@pytest.fixture
def fast() -> Timeouts:
    return FAST
