"""The cyclic exchange of cyclic synchronous position: RPDO targets, SYNC, the TPDOs of every drive
collected and tagged by SYNC counter, decoded to a :class:`CycleSample`.

The drives echo the counter of the SYNC they answer (manufacturer object 0x2010) in every TPDO:
a late TPDO is then dropped instead of being taken for the next cycle's. Drives without the echo
get a layout without it, and the TPDOs of a cycle are those received between its SYNC and the
deadline. TPDOs arrive in the bus notifier thread (:meth:`CycleExchanger.on_tpdo`).

Two ways to run a cycle:

- same cycle (:meth:`CycleExchanger.exchange`, lockstep and the master's own sequences): send the
  RPDOs and SYNC of cycle k, then wait for cycle k's TPDOs;
- pipelined (:meth:`CycleExchanger.send` then :meth:`CycleExchanger.collect` one cycle later,
  realtime): send SYNC k, then take the TPDOs of cycle k−1, which had a whole period to arrive,
  so that the caller's thread does not wait for the drives between its SYNCs. With the SYNC echo
  both cycles are open at once and each TPDO goes to the cycle its echo names; without it, a
  cycle's TPDOs are those received between its SYNC and the next one, so its collection is closed
  before the next SYNC goes out (see :class:`~drivegain.drivers.master.Master`).

Either way a sample holds the drives' answers to its own SYNC, with the targets sent in it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import can
import canopen
import numpy as np

from drivegain.drivers import objects as ob
from drivegain.drivers.bus import BusLoad, bus_load
from drivegain.drivers.cia402 import Command, State, decode_statusword
from drivegain.drivers.link import DriveLink, Timeouts, error_code, send
from drivegain.drivers.simtime import TimeBase
from drivegain.drivers.supervisor import Supervisor
from drivegain.errors import DriveError, TrajectoryError, UsageError
from drivegain.formats.log import EventLevel

_log = logging.getLogger(__name__)

#: Columns of :attr:`CycleSample.raw`, in order.
RAW_FIELDS = (
    "position",
    "torque_demand",
    "current",
    "torque",
    "statusword",
    "error_register",
    "mode",
    "sync_counter",
    "target",
)


@dataclass(frozen=True)
class CycleSample:
    """One SYNC cycle as the drives reported it.

    Attributes
    ----------
    cycle
        Cycle index: SYNCs sent by this master since it was created (no wrap).
    sync_time_ns
        Wall-clock time the SYNC was sent (``time.time_ns()``).
    position
        Joint positions, rad, joint side (coupling inverted), controller convention, (n,).
    current_reference
        Current references (torque demand 0x6074 × rated current 0x6075 / 1000), A, (n,).
    current
        Measured currents (0x6078 × rated current / 1000), A, (n,).
    raw
        Per joint, the values as sent: ``position`` (counts), ``torque_demand`` and ``current``
        and ``torque`` (per mille), ``statusword``, ``error_register``, ``mode``,
        ``sync_counter`` (the counter echoed in the TPDOs, or the counter of the SYNC sent when
        the drive does not echo it), ``target`` (counts sent in the RPDO).
    latency_s
        SYNC sent to last TPDO received, s, on the master's clock (in lockstep: the simulated
        delay of the last TPDO after its SYNC).
    sync_monotonic_s
        Monotonic time the SYNC was sent (``time.monotonic()``), s: for intervals between SYNCs.
    """

    cycle: int
    sync_time_ns: int
    position: np.ndarray
    current_reference: np.ndarray
    current: np.ndarray
    raw: dict[str, list[int]]
    latency_s: float = 0.0
    sync_monotonic_s: float = 0.0


@dataclass(frozen=True)
class SyncSent:
    """A SYNC the master sent, whose TPDOs are collected later (pipelined cycle).

    Attributes
    ----------
    cycle
        Cycle index (as :attr:`CycleSample.cycle`).
    sync_time_ns
        Wall-clock time the SYNC was sent (``time.time_ns()``).
    sync_monotonic_s
        Monotonic time the SYNC was sent (``time.monotonic()``), s.
    """

    cycle: int
    sync_time_ns: int
    sync_monotonic_s: float


@dataclass(frozen=True)
class PipelinedCycle:
    """What one :meth:`~drivegain.drivers.master.Master.cycle_pipelined` did.

    Attributes
    ----------
    sent
        The SYNC it sent (cycle k).
    sample
        The drives' answers to the previous SYNC (cycle k−1, its own SYNC times and targets);
        None when no cycle was in flight (the first of a stream).
    """

    sent: SyncSent
    sample: CycleSample | None


class InFlight:
    """One cycle whose TPDOs are being collected (filled in the notifier thread under the
    exchanger's lock).

    Attributes
    ----------
    cycle, counter
        Cycle index and its SYNC counter byte.
    counts
        Targets sent with this cycle's SYNC, encoder counts, (n,).
    frames
        Per joint, the decoded TPDO1 and TPDO2 (None until received).
    """

    __slots__ = (
        "complete",
        "counter",
        "counts",
        "cycle",
        "frames",
        "last_arrival",
        "missing",
        "sync_clock",
        "sync_mono_s",
        "sync_ns",
    )

    def __init__(self, cycle: int, counter: int, n: int, counts: np.ndarray):
        self.cycle = cycle
        self.counter = counter
        self.counts = counts
        self.frames: list[list[tuple[int, ...] | None]] = [[None, None] for _ in range(n)]
        self.missing = 2 * n
        self.last_arrival = 0.0
        self.complete = threading.Event()
        self.sync_ns = 0
        self.sync_mono_s = 0.0
        self.sync_clock = 0.0

    @property
    def sent(self) -> SyncSent:
        """When its SYNC went out."""
        return SyncSent(self.cycle, self.sync_ns, self.sync_mono_s)


class CycleExchanger:
    """RPDOs, SYNC and TPDO collection of every drive, one cycle at a time.

    Parameters
    ----------
    drives
        The drives, in joint order.
    network
        The connected network to send on.
    layout
        The PDO layout the drives were configured with.
    transmission
        Motor-from-joint transmission matrix (gear ratios and couplings), (n, n).
    sync_counter
        SYNC carries the counter byte (the drives know its overflow, 0x1019).
    timeouts
        ``tpdo_s``: SYNC to the last TPDO of the cycle, on the supervisor's clock.
    supervisor
        Faults and events; its :meth:`~Supervisor.check` explains a silent drive.

    Attributes
    ----------
    controlword
        Controlword sent in every RPDO (enable operation while streaming, quick stop, ...).
    targets
        Last targets sent, encoder counts, (n,).
    stale_frames
        TPDOs received outside their cycle (dropped).
    """

    def __init__(
        self,
        drives: Sequence[DriveLink],
        network: canopen.Network,
        layout: ob.PdoLayout,
        transmission: np.ndarray,
        *,
        sync_counter: bool,
        timeouts: Timeouts,
        supervisor: Supervisor,
    ):
        self.drives = tuple(drives)
        self.network = network
        self.layout = layout
        self.sync_counter = sync_counter
        self.timeouts = timeouts
        self.supervisor = supervisor
        self._k = transmission
        self._kinv = np.linalg.inv(transmission)
        self._cpr = np.array([d.cpr for d in self.drives])
        self._rpdo = ob.pdo_struct(layout.rpdo)
        self._tpdo_structs = tuple(ob.pdo_struct(t) for t in layout.tpdos)
        self._tagged = layout.tagged
        self._echo_at = tuple(
            t.index(ob.E_SYNC_ECHO) if ob.E_SYNC_ECHO in t else -1 for t in layout.tpdos
        )
        #: COB-ID -> (drive, TPDO number - 1), for the listener.
        self.tpdo_index: dict[int, tuple[DriveLink, int]] = {
            0x180 + 0x100 * k + d.node_id: (d, k) for d in self.drives for k in range(2)
        }
        # Collection of the cycles in flight (notifier thread <-> caller thread): one in the same
        # cycle exchange, two while a pipelined cycle k is sent and k-1 not yet collected.
        self._lock = threading.Lock()
        self._open: list[InFlight] = []
        # counters of cycles given up (quick stop after a fault): their late TPDOs are expected
        self._abandoned: deque[int] = deque(maxlen=4)
        self.stale_frames = 0
        self.cycle = 0
        self.controlword = int(Command.SHUTDOWN)
        self.targets = np.zeros(len(self.drives), dtype=np.int64)
        #: targets whose RPDOs :meth:`stage` sent for the next SYNC, if any
        self.staged: np.ndarray | None = None

    def bus_load(self, period_s: float, bitrate: int) -> BusLoad:
        """Bus load of this exchange every ``period_s`` s at ``bitrate`` bit/s."""
        rpdo, tpdo = self.layout.frame_bytes()
        sync_bytes = 1 if self.sync_counter else 0
        return bus_load(len(self.drives), period_s, bitrate, rpdo, tpdo, sync_bytes=sync_bytes)

    # --- conversions ---------------------------------------------------------------------------
    def target_counts(self, target: np.ndarray) -> np.ndarray:
        """Encoder counts of joint positions ``target`` (rad), (n,).

        Raises
        ------
        TrajectoryError
            Not n finite positions, or outside the 32-bit encoder range.
        """
        q = np.asarray(target, dtype=float)
        if q.shape != (len(self.drives),) or not np.all(np.isfinite(q)):
            raise TrajectoryError(f"target must be {len(self.drives)} finite positions, got {q}")
        counts = np.rint((self._k @ q) * self._cpr)
        if np.any(np.abs(counts) >= 2**31):
            raise TrajectoryError("target outside the 32-bit encoder range")
        return counts.astype(np.int64)

    def joint_positions(self, counts: np.ndarray) -> np.ndarray:
        """Joint positions (rad) of motor encoder ``counts``, (n,)."""
        return self._kinv @ (counts / self._cpr)

    # --- one cycle -----------------------------------------------------------------------------
    def exchange(self, counts: np.ndarray) -> CycleSample:
        """Send the RPDOs (``counts`` + :attr:`controlword`) and SYNC, wait for every TPDO
        (same cycle).

        Raises
        ------
        DriveError
            A fault pending in the supervisor, or a TPDO missing ``tpdo_s`` after SYNC (code
            0x8250).
        BusError
            The interface failed.
        """
        flight = self.send(counts)
        # on lockstep's simulated clock, a TPDO that cannot come any more is missing after
        # tpdo_s of simulated time, whatever the machine's load
        try:
            complete = self.supervisor.clock.wait(
                flight.complete, self.timeouts.tpdo_s, f"the TPDOs of cycle {flight.cycle}"
            )
        except BaseException:  # a hung simulation: nothing more to collect for this cycle
            self._forget(flight)
            raise
        return self._close(flight, complete, self.supervisor.clock.sync_time(flight.sync_clock))

    @property
    def in_flight(self) -> InFlight | None:
        """The oldest cycle sent and not collected yet, if any."""
        with self._lock:
            return self._open[0] if self._open else None

    def stage(self, counts: np.ndarray) -> None:
        """Send the RPDOs of the next SYNC now (``counts`` + :attr:`controlword`); :meth:`send`
        then sends the SYNC alone. The drives' RPDOs are synchronous: each drive holds what it
        received until the SYNC, so sending them ahead of the deadline changes nothing but
        the SYNC's own timing, which is then the pacer's alone.

        Raises
        ------
        BusError
            The interface failed (nothing is staged then).
        """
        self.staged = None
        self._send_rpdos(counts)
        self.staged = np.array(counts)

    def _send_rpdos(self, counts: np.ndarray) -> None:
        cw = self.controlword
        for d in self.drives:
            send(self.network, 0x200 + d.node_id, self._rpdo.pack(int(counts[d.joint]), cw))

    def send(self, counts: np.ndarray) -> InFlight:
        """Open cycle :attr:`cycle` for its TPDOs, send the RPDOs (``counts`` +
        :attr:`controlword`) unless :meth:`stage` sent them, and SYNC; the TPDOs are then taken
        by :meth:`collect`.

        Raises
        ------
        BusError
            The interface failed (the cycle is then given up).
        """
        staged, self.staged = self.staged, None
        if staged is not None and staged is not counts and not np.array_equal(staged, counts):
            raise UsageError("send: the targets differ from the ones staged for this SYNC")
        cycle = self.cycle
        counter = ob.sync_counter(cycle)
        flight = InFlight(cycle, counter, len(self.drives), counts)
        with self._lock:
            self._open.append(flight)
        try:
            if staged is None:
                self._send_rpdos(counts)
            flight.sync_ns = time.time_ns()
            flight.sync_mono_s = time.monotonic()
            flight.sync_clock = self.supervisor.clock.now()
            send(self.network, 0x80, bytes([counter]) if self.sync_counter else b"")
        except BaseException:
            self._forget(flight)
            raise
        self.cycle += 1
        return flight

    def collect(self, flight: InFlight) -> CycleSample:
        """The TPDOs of ``flight`` (sent earlier by :meth:`send`): wait for those still missing
        until ``tpdo_s`` after its own SYNC, then close it.

        Raises
        ------
        DriveError
            A fault pending in the supervisor, or a TPDO missing ``tpdo_s`` after its SYNC
            (code 0x8250).
        """
        clock = self.supervisor.clock
        left = self.timeouts.tpdo_s - (clock.now() - flight.sync_clock)
        try:
            complete = flight.complete.is_set() or clock.wait(
                flight.complete, max(0.0, left), f"the TPDOs of cycle {flight.cycle}"
            )
        except BaseException:
            self._forget(flight)
            raise
        # the SYNC's own send time: the clock's "last SYNC" is a later one by now
        return self._close(flight, complete, flight.sync_clock)

    def abandon(self) -> None:
        """Give up every cycle in flight (a quick stop, a new enable): their TPDOs, when they
        come, are dropped without an event. Staged RPDOs are forgotten: the next SYNC is sent
        with RPDOs of its own, which replace them in the drives."""
        self.staged = None
        with self._lock:
            for flight in self._open:
                self._abandoned.append(flight.counter)
            self._open.clear()

    def _forget(self, flight: InFlight) -> None:
        with self._lock:
            if flight in self._open:
                self._open.remove(flight)

    def _close(self, flight: InFlight, complete: bool, sync_at: float) -> CycleSample:
        """Close ``flight``: raise for a missing TPDO, else decode it (``sync_at``: its SYNC on
        the supervisor's clock, for the latency)."""
        self._forget(flight)
        with self._lock:
            frames = flight.frames
            last = flight.last_arrival
        if not complete:
            self.supervisor.check()  # a fault explains the silence better than the time-out
            for d in self.drives:
                for k in range(2):
                    if frames[d.joint][k] is None:
                        raise DriveError(
                            f"TPDO{k + 1} of cycle {flight.cycle} missing {self.timeouts.tpdo_s} s "
                            f"after SYNC",
                            node=d.node_id,
                            state=d.state,
                            code=int(ob.EmcyCode.PDO_TIMEOUT),
                        )
        return self._decode(
            flight.cycle,
            flight.sync_ns,
            flight.sync_mono_s,
            flight.counter,
            frames,
            flight.counts,
            last - sync_at,
        )

    def _decode(
        self,
        cycle: int,
        sync_ns: int,
        sync_mono_s: float,
        counter: int,
        frames: list[list[tuple[int, ...] | None]],
        counts: np.ndarray,
        latency: float,
    ) -> CycleSample:
        raw: dict[str, list[int]] = {name: [] for name in RAW_FIELDS}
        for d in self.drives:
            values: dict[str, int] = {"sync_counter": counter}
            for k, entries in enumerate(self.layout.tpdos):
                data = frames[d.joint][k]
                assert data is not None
                values.update({e.name: int(v) for e, v in zip(entries, data, strict=True)})
            values["target"] = int(counts[d.joint])
            for name, column in raw.items():
                column.append(values[name])
        rated = np.array([d.rated_a for d in self.drives])
        position = self.joint_positions(np.array(raw["position"], dtype=float))
        return CycleSample(
            cycle=cycle,
            sync_time_ns=sync_ns,
            sync_monotonic_s=sync_mono_s,
            position=position,
            current_reference=np.array(raw["torque_demand"], dtype=float) * rated / 1000.0,
            current=np.array(raw["current"], dtype=float) * rated / 1000.0,
            raw=raw,
            latency_s=max(0.0, latency),
        )

    def states(self, sample: CycleSample) -> list[State]:
        """The CiA 402 state of every drive in ``sample`` (recorded in the supervisor).

        Raises
        ------
        DriveError
            A statusword shows no CiA 402 state (code = statusword).
        """
        states = []
        for d, sw in zip(self.drives, sample.raw["statusword"], strict=True):
            state = decode_statusword(sw, node=d.node_id)
            self.supervisor.note_state(d, state)
            states.append(state)
        return states

    def check_sample(self, sample: CycleSample) -> None:
        """Raise if a drive of ``sample`` faulted or left OPERATION_ENABLED or CSP, or if the
        supervisor has a fault pending.

        Raises
        ------
        DriveError
            With node, state and (for a fault) the drive's error code 0x603F.
        """
        states = self.states(sample)
        self.supervisor.check()
        for d, state, mode in zip(self.drives, states, sample.raw["mode"], strict=True):
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                raise DriveError("drive in fault", node=d.node_id, state=state, code=error_code(d))
            if state != State.OPERATION_ENABLED:
                raise DriveError(
                    "drive left OPERATION_ENABLED",
                    node=d.node_id,
                    state=state,
                    code=error_code(d),
                )
            if mode != ob.MODE_CSP:
                raise DriveError(
                    f"drive left cyclic synchronous position mode (mode {mode})",
                    node=d.node_id,
                    state=state,
                )

    # --- reception (notifier thread) -----------------------------------------------------------
    def on_tpdo(self, d: DriveLink, k: int, data: bytes, sent: float) -> None:
        """TPDO ``k + 1`` of drive ``d``, sent at ``sent`` (the supervisor's clock): file it in
        the cycle in flight, or drop it."""
        layout = self._tpdo_structs[k]
        if len(data) < layout.size:
            self.supervisor.add_fault(
                DriveError(
                    f"TPDO{k + 1} has {len(data)} bytes, the mapping needs {layout.size}",
                    node=d.node_id,
                    code=0x8210,
                )
            )
            return
        values = layout.unpack_from(data)
        with self._lock:
            if not self._open:
                self.stale_frames += 1
                return
            if self._tagged:
                echo = values[self._echo_at[k]]
                flight = next((f for f in self._open if f.counter == echo), None)
                if flight is None:
                    self.stale_frames += 1
                    if echo not in self._abandoned:
                        self.supervisor.event(
                            EventLevel.WARNING,
                            d.node_id,
                            None,
                            f"TPDO{k + 1} of SYNC {echo} arrived during SYNC "
                            f"{self._open[-1].counter}: dropped",
                        )
                    return
            else:
                # no echo: the cycle whose SYNC came last (only one is open at a time)
                flight = self._open[-1]
            slot = flight.frames[d.joint]
            if slot[k] is None:
                flight.missing -= 1
            slot[k] = values
            if flight.missing == 0:
                flight.last_arrival = sent
                flight.complete.set()


class FrameDispatcher(can.Listener):
    """Hands every frame of the bus to the part of the master that handles it: TPDOs to the
    exchanger, heartbeats, EMCYs and error frames to the supervisor (runs in the notifier
    thread)."""

    def __init__(self, exchanger: CycleExchanger, supervisor: Supervisor, clock: TimeBase):
        self.exchanger = exchanger
        self.supervisor = supervisor
        self.clock = clock

    def on_message_received(self, msg: can.Message) -> None:
        try:
            self._dispatch(msg)
        except Exception as exc:  # never let one frame kill the reader thread
            _log.exception("drive master: frame handling failed")
            self.supervisor.add_fault(DriveError(f"internal error handling a frame: {exc!r}"))

    def _dispatch(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.supervisor.on_error_frame(msg)
            return
        if msg.is_remote_frame:
            return
        cob = msg.arbitration_id
        hit = self.exchanger.tpdo_index.get(cob)
        if hit is not None:
            self.exchanger.on_tpdo(hit[0], hit[1], bytes(msg.data), self.clock.stamp(msg))
            return
        node_id = cob & 0x7F
        d = self.supervisor.by_node.get(node_id)
        if d is None:
            return
        function = cob & 0x780
        if function == 0x700 and msg.dlc >= 1:
            self.supervisor.on_heartbeat(d, msg.data[0] & 0x7F, self.clock.stamp(msg))
        elif function == 0x080 and node_id != 0:
            self.supervisor.on_emcy(d, bytes(msg.data))

    def stop(self) -> None:
        """Nothing to release."""
