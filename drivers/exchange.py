"""The cyclic exchange of cyclic synchronous position: RPDO targets, SYNC, the TPDOs of every drive
collected and tagged by SYNC counter, decoded to a :class:`CycleSample`.

The drives echo the counter of the SYNC they answer (manufacturer object 0x2010) in every TPDO:
a late TPDO is then dropped instead of being taken for the next cycle's. Drives without the echo
get a layout without it, and the TPDOs of a cycle are those received between its SYNC and the
deadline. TPDOs arrive in the bus notifier thread (:meth:`CycleExchanger.on_tpdo`); the caller's
thread waits for the last one of the cycle.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import canopen
import numpy as np

from drivegain.drivers import objects as ob
from drivegain.drivers.bus import BusLoad, bus_load
from drivegain.drivers.cia402 import Command, State, decode_statusword
from drivegain.drivers.link import DriveLink, Timeouts, error_code, send
from drivegain.drivers.supervisor import Supervisor
from drivegain.errors import DriveError, TrajectoryError
from drivegain.formats.log import EventLevel

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
        # Collection of the cycle in flight (notifier thread <-> caller thread).
        self._lock = threading.Lock()
        self._pending: int | None = None  # SYNC counter of the cycle being collected
        self._frames: list[list[tuple[int, ...] | None]] = []
        self._missing = 0
        self._last_arrival = 0.0
        self._complete = threading.Event()
        self.stale_frames = 0
        self.cycle = 0
        self.controlword = int(Command.SHUTDOWN)
        self.targets = np.zeros(len(self.drives), dtype=np.int64)

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
        """Send the RPDOs (``counts`` + :attr:`controlword`) and SYNC, wait for every TPDO.

        Raises
        ------
        DriveError
            A fault pending in the supervisor, or a TPDO missing ``tpdo_s`` after SYNC (code
            0x8250).
        BusError
            The interface failed.
        """
        cycle = self.cycle
        counter = ob.sync_counter(cycle)
        n = len(self.drives)
        with self._lock:
            self._pending = counter
            self._frames = [[None, None] for _ in range(n)]
            self._missing = 2 * n
            self._complete.clear()
        cw = self.controlword
        for d in self.drives:
            send(self.network, 0x200 + d.node_id, self._rpdo.pack(int(counts[d.joint]), cw))
        sync_ns = time.time_ns()
        t_sync = time.monotonic()
        sync_clock = self.supervisor.clock.now()
        send(self.network, 0x80, bytes([counter]) if self.sync_counter else b"")
        # on lockstep's simulated clock, a TPDO that cannot come any more is missing after
        # tpdo_s of simulated time, whatever the machine's load
        complete = self.supervisor.clock.wait(
            self._complete, self.timeouts.tpdo_s, f"the TPDOs of cycle {cycle}"
        )
        with self._lock:
            frames = self._frames
            self._pending = None
            last = self._last_arrival
        self.cycle += 1
        if not complete:
            self.supervisor.check()  # a fault explains the silence better than the time-out
            for d in self.drives:
                for k in range(2):
                    if frames[d.joint][k] is None:
                        raise DriveError(
                            f"TPDO{k + 1} of cycle {cycle} missing {self.timeouts.tpdo_s} s "
                            f"after SYNC",
                            node=d.node_id,
                            state=d.state,
                            code=int(ob.EmcyCode.PDO_TIMEOUT),
                        )
        latency = last - self.supervisor.clock.sync_time(sync_clock)
        return self._decode(cycle, sync_ns, t_sync, counter, frames, counts, latency)

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
            pending = self._pending
            if pending is None:
                self.stale_frames += 1
                return
            if self._tagged:
                echo = values[self._echo_at[k]]
                if echo != pending:
                    self.stale_frames += 1
                    self.supervisor.event(
                        EventLevel.WARNING,
                        d.node_id,
                        None,
                        f"TPDO{k + 1} of SYNC {echo} arrived during SYNC {pending}: dropped",
                    )
                    return
            slot = self._frames[d.joint]
            if slot[k] is None:
                self._missing -= 1
            slot[k] = values
            if self._missing == 0:
                self._last_arrival = sent
                self._complete.set()
