"""Supervision of the drives and the bus: heartbeat consumer, EMCY, CAN error frames, faults and
events.

canopen's own reception is not used for this (one failing callback silently skips the others on
the same CAN id, error frames are dropped, the EMCY log grows without bound, there is no
heartbeat time-out). The master's listener hands every heartbeat, EMCY and error frame to a
:class:`Supervisor` in the bus notifier thread; faults noticed there wait in a list until the
caller's thread asks (:meth:`Supervisor.check`, called by every cycle), so that they are raised
where they can be handled.

Reaction time: a fault noticed here (EMCY, heartbeat time-out, NMT state, bus) is raised before
the next SYNC, in the same-cycle and the pipelined exchange alike; what the TPDOs of cycle k show
is raised after SYNC k (same cycle) or after SYNC k+1 (pipelined, one period later); see
:mod:`.master` and docs/realtime.md.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import can
import canopen

from drivegain.drivers import objects as ob
from drivegain.drivers.cia402 import State
from drivegain.drivers.link import DriveLink, Timeouts
from drivegain.drivers.simtime import TimeBase
from drivegain.errors import BusError, DriveError
from drivegain.formats.log import EventLevel

NMT_NAMES = {0x00: "BOOT-UP", 0x04: "STOPPED", 0x05: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}
NMT_OPERATIONAL = 0x05
#: socketcan error classes (python-can keeps them in ``arbitration_id`` of error frames).
_ERR_CRTL = 0x04
_ERR_BUSOFF = 0x40
_ERR_CRTL_PASSIVE = 0x10 | 0x20  # data[1]: RX / TX error passive
#: Error frames (other than bus-off / error passive) tolerated per second before giving up.
ERROR_FRAMES_PER_S = 10


@dataclass(frozen=True)
class DriveEvent:
    """Something worth logging: EMCY, NMT or CiA 402 state change, fault, warning.

    Attributes
    ----------
    time_ns
        Wall-clock time it was noticed (``time.time_ns()``).
    level
        Severity, as the log's ``/events`` channel holds it.
    node
        CANopen node id, or ``None`` for the bus or every drive.
    code
        EMCY or error code, if any.
    text
        One line for a human.
    """

    time_ns: int
    level: EventLevel
    node: int | None
    code: int | None
    text: str


class Supervisor:
    """Heartbeat consumer, EMCY and error-frame handler, fault and event queues.

    Parameters
    ----------
    drives
        The drives, in joint order (their ``nmt``, ``last_heartbeat`` and ``state`` are kept
        up to date here).
    network
        The connected network (its notifier and bus are checked for failures).
    timeouts
        Time limits (heartbeat consumer time-out).
    clock
        The clock the time-outs count (wall, or lockstep's simulated clock).

    Notes
    -----
    The ``on_*`` methods run in the bus notifier thread, everything else in the caller's.
    """

    def __init__(
        self,
        drives: Sequence[DriveLink],
        network: canopen.Network,
        timeouts: Timeouts,
        clock: TimeBase,
    ):
        self.drives = tuple(drives)
        self.network = network
        self.timeouts = timeouts
        self.clock = clock
        self.by_node = {d.node_id: d for d in self.drives}
        self._lock = threading.Lock()
        self._events: deque[DriveEvent] = deque(maxlen=10_000)
        self._faults: list[DriveError] = []
        self._error_frames: deque[float] = deque(maxlen=ERROR_FRAMES_PER_S + 1)
        #: Set by the boot-up message / first OPERATIONAL heartbeat of each node.
        self.bootup = {d.node_id: threading.Event() for d in self.drives}
        self.operational = {d.node_id: threading.Event() for d in self.drives}
        #: Heartbeat consumer on: leaving OPERATIONAL or going silent is a fault.
        self.monitoring = False

    # --- faults and events (any thread) --------------------------------------------------------
    def event(self, level: EventLevel, node: int | None, code: int | None, text: str) -> None:
        """Queue an event for :meth:`drain_events`."""
        self._events.append(DriveEvent(time.time_ns(), level, node, code, text))

    def add_fault(self, fault: DriveError) -> None:
        """Queue a fault for the next :meth:`check`."""
        with self._lock:
            self._faults.append(fault)

    def clear_faults(self) -> None:
        """Forget the faults not yet raised (a new boot or enable starts afresh)."""
        with self._lock:
            self._faults.clear()

    def note_state(self, d: DriveLink, state: State) -> None:
        """Record the CiA 402 state seen of a drive, with an event when it changed."""
        if state != d.state:
            old = d.state.name if d.state else "unknown"
            faulted = state in (State.FAULT, State.FAULT_REACTION_ACTIVE)
            level = EventLevel.ERROR if faulted else EventLevel.INFO
            self.event(level, d.node_id, None, f"CiA 402 {old} -> {state.name}")
            d.state = state

    def drain_events(self) -> list[DriveEvent]:
        """Events since the last call, oldest first."""
        for d in self.drives:
            d.node.emcy.reset()  # canopen's own EMCY log (unused here) must not grow
        out = []
        with self._lock:
            while self._events:
                out.append(self._events.popleft())
        return out

    # --- checks (caller's thread) --------------------------------------------------------------
    def check(self) -> None:
        """Raise a pending fault (EMCY, heartbeat time-out, NMT state, bus) now.

        Raises
        ------
        DriveError
            The oldest fault noticed since the last call, with the drive's CiA 402 state.
        BusError
            The bus reader stopped, the bus is closed or the controller is bus-off.
        """
        self.check_bus()
        if self.monitoring:
            self.check_heartbeats()
        with self._lock:
            fault = self._faults.pop(0) if self._faults else None
        if fault is not None:
            d = self.by_node.get(fault.node) if fault.node is not None else None
            if d is not None and d.state is not None and fault.state is None:
                # Noticed in the reader thread: report the state seen since.
                fault = type(fault)(fault.message, node=fault.node, state=d.state, code=fault.code)
            raise fault

    def check_bus(self) -> None:
        """Raise :class:`BusError` if the bus reader stopped or the controller is bus-off."""
        notifier = self.network.notifier
        if notifier is not None and notifier.exception is not None:
            raise BusError(f"CAN reader stopped: {notifier.exception}")
        bus = self.network.bus
        if bus is None:
            raise BusError("the CAN bus is closed")
        try:
            bus_state = bus.state
        except Exception:  # an interface without state reporting
            return
        if bus_state == can.BusState.ERROR:
            raise BusError("CAN controller is bus-off", code=int(ob.EmcyCode.BUS_OFF))

    def check_heartbeats(self) -> None:
        """Queue a fault for every drive silent longer than the consumer time-out (once per
        time-out period of silence)."""
        now = self.clock.now()
        limit = self.timeouts.heartbeat_s
        for d in self.drives:
            if d.last_heartbeat is None or now - max(d.last_heartbeat, d.silence_reported) <= limit:
                continue
            silent = now - d.last_heartbeat
            d.silence_reported = now
            self.add_fault(
                DriveError(
                    f"no heartbeat for {silent:.3f} s (limit {limit} s)",
                    node=d.node_id,
                    code=int(ob.EmcyCode.HEARTBEAT),
                )
            )

    def alive(self, d: DriveLink) -> bool:
        """False for a drive whose heartbeat stopped: on the way down, do not wait for SDO
        answers that cannot come."""
        if (
            d.last_heartbeat is None
            or self.clock.now() - d.last_heartbeat <= self.timeouts.heartbeat_s
        ):
            return True
        self.event(EventLevel.WARNING, d.node_id, None, "no heartbeat: drive skipped")
        return False

    def start_consumer(self) -> None:
        """Start the heartbeat consumer now (every drive counts as just heard)."""
        now = self.clock.now()
        for d in self.drives:
            d.last_heartbeat = now
        self.monitoring = True

    def await_nmt(self, flags: dict[int, threading.Event], what: str) -> None:
        """Wait until every node's flag (:attr:`bootup` or :attr:`operational`) is set.

        Raises
        ------
        DriveError
            A node did not within ``boot_s`` (code 0x8130, heartbeat / boot-up error).
        """
        deadline = self.clock.now() + self.timeouts.boot_s
        for d in self.drives:
            left = deadline - self.clock.now()
            if not self.clock.wait(flags[d.node_id], left, f"{what} (node {d.node_id})"):
                raise DriveError(
                    f"{what} within {self.timeouts.boot_s} s",
                    node=d.node_id,
                    code=int(ob.EmcyCode.HEARTBEAT),
                )

    # --- reception (notifier thread) -----------------------------------------------------------
    def on_heartbeat(self, d: DriveLink, state: int, sent: float) -> None:
        """A heartbeat (or boot-up, state 0) of node ``d``, sent at ``sent`` (master's clock)."""
        d.last_heartbeat = sent
        previous, d.nmt = d.nmt, state
        if state == 0:
            self.bootup[d.node_id].set()
        if state == NMT_OPERATIONAL:
            self.operational[d.node_id].set()
        if state != previous:
            name = NMT_NAMES.get(state, f"0x{state:02X}")
            level = EventLevel.INFO
            if self.monitoring and state != NMT_OPERATIONAL:
                level = EventLevel.ERROR
                self.add_fault(
                    DriveError(
                        f"node left OPERATIONAL (NMT {name})",
                        node=d.node_id,
                        code=int(ob.EmcyCode.HEARTBEAT),
                    )
                )
            self.event(level, d.node_id, None, f"NMT {name}")

    def on_emcy(self, d: DriveLink, data: bytes) -> None:
        """An EMCY of node ``d``: a fault, unless it is the error reset (code 0)."""
        if len(data) < 2:
            return
        code = int.from_bytes(data[0:2], "little")
        register = data[2] if len(data) > 2 else 0
        if code == 0:
            self.event(EventLevel.INFO, d.node_id, 0, "EMCY error reset")
            return
        text = f"EMCY 0x{code:04X} (error register 0x{register:02X})"
        self.event(EventLevel.ERROR, d.node_id, code, text)
        self.add_fault(DriveError(text, node=d.node_id, code=code))

    def on_error_frame(self, msg: can.Message) -> None:
        """A CAN error frame: bus-off and error passive are faults at once, other error frames
        only past :data:`ERROR_FRAMES_PER_S` per second."""
        cls = msg.arbitration_id
        data = bytes(msg.data)
        if cls & _ERR_BUSOFF:
            self.event(EventLevel.ERROR, None, int(ob.EmcyCode.BUS_OFF), "CAN bus-off")
            self.add_fault(BusError("CAN bus-off", code=int(ob.EmcyCode.BUS_OFF)))
            return
        if cls & _ERR_CRTL and len(data) > 1 and data[1] & _ERR_CRTL_PASSIVE:
            passive = int(ob.EmcyCode.CAN_ERROR_PASSIVE)
            self.event(EventLevel.ERROR, None, passive, "CAN error passive")
            self.add_fault(BusError("CAN controller error passive", code=passive))
            return
        now = self.clock.now()
        self._error_frames.append(now)
        self.event(EventLevel.WARNING, None, None, f"CAN error frame (class 0x{cls:X})")
        if len(self._error_frames) > ERROR_FRAMES_PER_S and now - self._error_frames[0] < 1.0:
            self._error_frames.clear()
            self.add_fault(
                BusError(
                    f"more than {ERROR_FRAMES_PER_S} CAN error frames per second",
                    code=int(ob.EmcyCode.CAN_OVERRUN),
                )
            )
