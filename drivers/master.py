"""The master side: CiA 402 drives in cyclic synchronous position mode over CANopen.

One :class:`Master` drives every joint of a robot through canopen ``RemoteNode``s on a connected
:class:`canopen.Network`. It does not care whether the drives are real or simulated: the bus
configuration is the only difference.

Reception does not use canopen's per-id callbacks (one failing callback silently skips the others,
error frames are dropped, the EMCY log grows without bound, there is no heartbeat time-out). The
master adds one :class:`can.Listener` to the network's notifier instead, which sees every frame:
TPDOs (collected per cycle and tagged by the SYNC counter echoed by the drives), heartbeats
(consumer with time-out), EMCYs and error frames. Faults noticed there are raised by the next
:meth:`Master.cycle` or :meth:`Master.check` in the caller's thread, as :class:`DriveError`.
"""

from __future__ import annotations

import contextlib
import logging
import struct
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import canopen
import numpy as np
from canopen.objectdictionary import ObjectDictionary, import_od
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivegain.config.robot import Robot
from drivegain.drivers import gcfreeze
from drivegain.drivers import objects as ob
from drivegain.drivers.bus import BusLoad, bus_load
from drivegain.drivers.cia402 import (
    POWERED,
    Command,
    State,
    command_towards,
    decode_statusword,
)
from drivegain.errors import BusError, ConfigError, DriveError, TrajectoryError

logger = logging.getLogger(__name__)

_NMT_NAMES = {0x00: "BOOT-UP", 0x04: "STOPPED", 0x05: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}
_NMT_OPERATIONAL = 0x05
#: socketcan error classes (python-can keeps them in ``arbitration_id`` of error frames).
_ERR_CRTL = 0x04
_ERR_BUSOFF = 0x40
_ERR_CRTL_PASSIVE = 0x10 | 0x20  # data[1]: RX / TX error passive
#: Error frames (other than bus-off / error passive) tolerated per second before giving up.
ERROR_FRAMES_PER_S = 10


@dataclass(frozen=True)
class Timeouts:
    """Time limits of the master (seconds).

    Attributes
    ----------
    boot_s
        NMT reset to boot-up, and NMT start to the first OPERATIONAL heartbeat.
    sdo_s
        One SDO response (canopen retries once).
    state_s
        One CiA 402 transition.
    heartbeat_producer_s
        Heartbeat period written to every drive (0x1017).
    heartbeat_s
        Heartbeat consumer time-out: a drive silent this long is lost.
    tpdo_s
        SYNC to the last TPDO of the cycle. Keep it below the period for real-time loops; the
        default tolerates a loaded machine running the simulator in lockstep.
    quick_stop_s
        Longest wait for the drives to come to rest after a quick stop.
    poll_s
        Pause between statusword polls.
    """

    boot_s: float = 2.0
    sdo_s: float = 0.5
    state_s: float = 1.0
    heartbeat_producer_s: float = 0.1
    heartbeat_s: float = 0.35
    tpdo_s: float = 0.25
    quick_stop_s: float = 3.0
    poll_s: float = 0.002

    def __post_init__(self) -> None:
        for name in ("boot_s", "sdo_s", "state_s", "heartbeat_producer_s", "heartbeat_s", "tpdo_s"):
            if getattr(self, name) <= 0.0:
                raise ConfigError(f"timeout {name} must be > 0, got {getattr(self, name)}")
        if self.heartbeat_s <= self.heartbeat_producer_s:
            raise ConfigError(
                f"heartbeat_s ({self.heartbeat_s}) must exceed heartbeat_producer_s "
                f"({self.heartbeat_producer_s})"
            )
        if not 1 <= round(self.heartbeat_producer_s * 1000) <= 0xFFFF:
            raise ConfigError("heartbeat_producer_s must be 0.001..65.535 s")


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
        SYNC sent to last TPDO received, s.
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
class DriveEvent:
    """Something worth logging: EMCY, NMT or CiA 402 state change, fault, warning."""

    time_ns: int
    level: str  # "info" | "warning" | "error"
    node: int | None
    code: int | None
    text: str


@dataclass
class _Drive:
    joint: int
    node_id: int
    node: canopen.RemoteNode
    cpr: float  # encoder counts per motor radian
    rated_a: float
    nmt: int | None = None
    last_heartbeat: float | None = None
    silence_reported: float = 0.0
    state: State | None = None


class _Listener(can.Listener):
    """Forwards every frame of the bus to the master (runs in the notifier thread)."""

    def __init__(self, master: Master):
        self.master = master

    def on_message_received(self, msg: can.Message) -> None:
        try:
            self.master._on_frame(msg)
        except Exception as exc:  # never let one frame kill the reader thread
            logger.exception("drive master: frame handling failed")
            self.master._add_fault(DriveError(f"internal error handling a frame: {exc!r}"))

    def stop(self) -> None:
        """Nothing to release."""


class Master:
    """CiA 402 drives of one robot, cyclic synchronous position.

    Parameters
    ----------
    robot
        The robot: joint order, node ids, gear ratios, couplings, encoder counts.
    network
        A connected network (see :func:`drivegain.drivers.bus.open_network`); the caller
        disconnects it after :meth:`close`.
    period_s
        SYNC period, s (written to the drives as interpolation period 0x60C2).
    eds
        The drives' EDS (default: the shipped ``cia402-servo.eds``). The master uses only
        standard CiA 301/402 objects, plus the SYNC echo 0x2010 if the EDS has it.
    timeouts
        Time limits.

    Notes
    -----
    From :meth:`boot` to :meth:`close` the master holds :mod:`.gcfreeze`: full collections of
    the garbage collector walk the whole process (0.1-0.26 s measured in the test suite) and
    would otherwise stall TPDO collection and heartbeat supervision beyond their time-outs.
    """

    def __init__(
        self,
        robot: Robot,
        network: canopen.Network,
        *,
        period_s: float,
        eds: Path | None = None,
        timeouts: Timeouts | None = None,
    ):
        if network.notifier is None or network.bus is None:
            raise BusError("the CANopen network is not connected")
        try:
            self._interp = ob.interpolation_period(period_s)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        self.robot = robot
        self.network = network
        self.period_s = period_s
        self.timeouts = timeouts or Timeouts()
        self.eds = Path(eds) if eds is not None else ob.default_eds()
        self._k = robot.transmission()
        self._kinv = np.linalg.inv(self._k)
        self._drives: list[_Drive] = []
        self._by_node: dict[int, _Drive] = {}
        od_probe: ObjectDictionary | None = None
        for j, joint in enumerate(robot.joints):
            try:
                od = import_od(str(self.eds), joint.node_id)
            except Exception as exc:
                raise ConfigError(f"cannot read the EDS ({exc})", file=self.eds) from None
            od_probe = od_probe or od
            node = canopen.RemoteNode(joint.node_id, od)
            node.sdo.RESPONSE_TIMEOUT = self.timeouts.sdo_s
            network.add_node(node)
            drive = _Drive(
                joint=j,
                node_id=joint.node_id,
                node=node,
                cpr=ob.counts_per_radian(joint.encoder_counts),
                rated_a=joint.rated_current,
            )
            self._drives.append(drive)
            self._by_node[joint.node_id] = drive
        assert od_probe is not None
        self._od = od_probe
        # SYNC carries a counter only if the drives know its overflow value (0x1019); otherwise
        # they may reject it ("unexpected SYNC data length").
        self._sync_counter = ob.SYNC_OVERFLOW in od_probe
        echo = od_probe.get(ob.SYNC_ECHO)
        tagged = self._sync_counter and echo is not None and getattr(echo, "pdo_mappable", False)
        self.layout = ob.TAGGED_LAYOUT if tagged else ob.PLAIN_LAYOUT
        self._tpdo_structs = tuple(ob.pdo_struct(t) for t in self.layout.tpdos)
        self._tagged = self.layout.tagged
        self._echo_at = tuple(
            t.index(ob.E_SYNC_ECHO) if ob.E_SYNC_ECHO in t else -1 for t in self.layout.tpdos
        )
        self._tpdo_index: dict[int, tuple[_Drive, int]] = {}
        for d in self._drives:
            for k in range(2):
                self._tpdo_index[0x180 + 0x100 * k + d.node_id] = (d, k)
        self._rpdo = ob.pdo_struct(self.layout.rpdo)
        # Cross-thread state (listener thread <-> caller thread).
        self._lock = threading.Lock()
        self._events: deque[DriveEvent] = deque(maxlen=10_000)
        self._faults: list[DriveError] = []
        self._bootup = {d.node_id: threading.Event() for d in self._drives}
        self._operational = {d.node_id: threading.Event() for d in self._drives}
        self._monitoring = False
        self._error_frames: deque[float] = deque(maxlen=ERROR_FRAMES_PER_S + 1)
        # Cycle collection.
        self._pending: int | None = None  # SYNC counter of the cycle being collected
        self._frames: list[list[tuple[int, ...] | None]] = []
        self._missing = 0
        self._last_arrival = 0.0
        self._complete = threading.Event()
        self.stale_frames = 0
        # Cyclic state.
        self._cycle = 0
        self._controlword = int(Command.SHUTDOWN)
        self._targets = np.zeros(robot.n, dtype=np.int64)
        self._streaming = False
        self._booted = False
        self._closed = False
        self._gc_held = False  # this master holds the collector's freeze (boot to close)
        self._listener = _Listener(self)
        network.notifier.add_listener(self._listener)

    # --- public API ----------------------------------------------------------------------------
    @property
    def node_ids(self) -> list[int]:
        return [d.node_id for d in self._drives]

    @property
    def states(self) -> dict[int, State | None]:
        """Last CiA 402 state seen of each node."""
        return {d.node_id: d.state for d in self._drives}

    @property
    def cycle_index(self) -> int:
        """Index the next :meth:`cycle` will carry."""
        return self._cycle

    def bus_load(self, bitrate: int) -> BusLoad:
        """Bus load of this master's cyclic exchange at ``bitrate``."""
        rpdo, tpdo = self.layout.frame_bytes()
        sync_bytes = 1 if self._sync_counter else 0
        return bus_load(
            len(self._drives), self.period_s, bitrate, rpdo, tpdo, sync_bytes=sync_bytes
        )

    def boot(self) -> None:
        """NMT reset communication, boot-up, SDO configuration, NMT start.

        Configuration per drive: device type (CiA 402), CSP support (0x6502), rated current
        (0x6075), encoder resolution (0x608F, checked against the robot file), PDO mapping (RPDO1
        target + controlword, TPDO1/TPDO2 synchronous, others disabled), SYNC counter overflow
        (0x1019), heartbeat producer (0x1017), interpolation period (0x60C2), mode of operation
        0x6060 = 8 (checked in 0x6061).

        Raises
        ------
        DriveError
            A drive did not boot, refused a setting or is not a CSP-capable CiA 402 drive.
        ConfigError
            A drive disagrees with the robot file (encoder resolution).
        """
        self._monitoring = False
        self._streaming = False
        self._booted = False
        if not self._gc_held:
            # From here on, time-outs are tighter than a full collection of this process.
            gcfreeze.hold()
            self._gc_held = True
        with self._lock:
            self._faults.clear()
        for d in self._drives:
            self._bootup[d.node_id].clear()
            self._operational[d.node_id].clear()
        for d in self._drives:
            self._send(0x000, bytes([0x82, d.node_id]))
        self._await(self._bootup, "no boot-up message after NMT reset communication")
        for d in self._drives:
            self._configure(d)
        for d in self._drives:
            self._operational[d.node_id].clear()
            self._send(0x000, bytes([0x01, d.node_id]))
        self._await(self._operational, "no OPERATIONAL heartbeat after NMT start")
        now = time.monotonic()
        for d in self._drives:
            d.last_heartbeat = now
        self._monitoring = True
        self._booted = True
        self._event("info", None, None, f"{len(self._drives)} drives booted and operational")

    def enable(self) -> None:
        """Bring every drive to OPERATION_ENABLED, holding its actual position.

        Faults are reset (rising edge of controlword bit 7), a quick stop is ended by "disable
        voltage"; then the target 0x607A is set to the actual position 0x6064 and the drive is
        walked through READY_TO_SWITCH_ON and SWITCHED_ON. Every transition has a time-out.

        Raises
        ------
        DriveError
            A transition timed out or a fault could not be reset.
        """
        self._require_booted()
        self._streaming = False
        with self._lock:
            self._faults.clear()
        for d in self._drives:
            d.node.emcy.reset()  # canopen's own EMCY log, unused here, must not grow
        first = {d.node_id: self._read_state(d) for d in self._drives}
        for d in self._drives:
            if first[d.node_id] in (
                State.FAULT,
                State.FAULT_REACTION_ACTIVE,
                State.QUICK_STOP_ACTIVE,
                State.NOT_READY_TO_SWITCH_ON,
            ):
                self._walk(d, State.SWITCH_ON_DISABLED, first[d.node_id])
        for d in self._drives:
            counts = self._upload(d, ob.POSITION_ACTUAL, 0, "i")
            self._download(d, ob.TARGET_POSITION, 0, "i", counts)
            self._targets[d.joint] = counts
        for d in self._drives:
            self._walk(d, State.OPERATION_ENABLED)
        self._controlword = int(Command.ENABLE_OPERATION)
        self._streaming = True
        self._event("info", None, None, "drives enabled (OPERATION_ENABLED)")

    def read_positions(self) -> np.ndarray:
        """Joint positions (rad) read by SDO from 0x6064."""
        self._require_booted()
        counts = np.array([self._upload(d, ob.POSITION_ACTUAL, 0, "i") for d in self._drives])
        return self._joint_positions(counts)

    def cycle(self, target: np.ndarray) -> CycleSample:
        """One SYNC cycle: RPDOs (target 0x607A + controlword), SYNC with counter, then wait for
        both TPDOs of every drive tagged with this SYNC.

        Parameters
        ----------
        target
            Joint positions to reach one period later, rad, (n,).

        Raises
        ------
        DriveError
            A drive faulted (statusword, EMCY), left OPERATION_ENABLED or CSP, went silent
            (heartbeat), or a TPDO of the cycle is missing (code 0x8250); node and code set.
        BusError
            Bus-off, error-passive or repeated error frames, or the interface failed.
        TrajectoryError
            ``target`` is not finite or outside the encoder range.
        """
        self._require_booted()
        if not self._streaming:
            raise DriveError("the drives are not enabled (call enable() first)")
        self.check()
        self._targets = self._target_counts(target)
        sample = self._exchange(self._targets)
        self._check_sample(sample)
        return sample

    def check(self) -> None:
        """Raise a pending fault (EMCY, heartbeat time-out, NMT state, bus) now."""
        self._check_bus()
        if self._monitoring:
            self._check_heartbeats()
        with self._lock:
            fault = self._faults.pop(0) if self._faults else None
        if fault is not None:
            d = self._by_node.get(fault.node) if fault.node is not None else None
            if d is not None and d.state is not None and fault.state is None:
                # Noticed in the reader thread: report the state seen since.
                fault = type(fault)(
                    fault.message, node=fault.node, state=d.state.name, code=fault.code
                )
            raise fault

    def drain_events(self) -> list[DriveEvent]:
        """Events since the last call, oldest first."""
        for d in self._drives:
            d.node.emcy.reset()  # canopen's own EMCY log (unused here) must not grow
        out = []
        with self._lock:
            while self._events:
                out.append(self._events.popleft())
        return out

    def quick_stop(self) -> None:
        """Quick stop every drive and keep SYNC going until they rest (never raises)."""
        if not self._booted:
            return
        try:
            self._streaming = False
            self._controlword = int(Command.QUICK_STOP)
            for d in self._drives:
                if not self._alive(d):
                    continue
                try:
                    self._download(d, ob.CONTROLWORD, 0, "H", self._controlword)
                except Exception as exc:
                    self._event("error", d.node_id, None, f"quick stop by SDO failed: {exc}")
            deadline = time.monotonic() + self.timeouts.quick_stop_s
            next_t = time.monotonic()
            while time.monotonic() < deadline:
                try:
                    sample = self._exchange(self._targets)
                except DriveError as exc:
                    self._event("error", exc.node, exc.code, f"during quick stop: {exc}")
                    break
                states = [decode_statusword(s) for s in sample.raw["statusword"]]
                for d, state in zip(self._drives, states, strict=True):
                    self._note_state(d, state)
                if not any(s in POWERED for s in states):
                    break
                next_t += self.period_s
                time.sleep(max(0.0, next_t - time.monotonic()))
            self._event("warning", None, None, "quick stop")
        except Exception as exc:
            self._event("error", None, None, f"quick stop failed: {exc}")

    def disable(self) -> None:
        """Switch every drive's power stage off ("shutdown", brakes hold); never raises."""
        if not self._booted:
            return
        self._streaming = False
        self._controlword = int(Command.SHUTDOWN)
        for d in self._drives:
            if not self._alive(d):
                continue
            # QUICK STOP ACTIVE ignores "shutdown": only "disable voltage" leaves it (CiA 402).
            cw = (
                int(Command.DISABLE_VOLTAGE)
                if d.state == State.QUICK_STOP_ACTIVE
                else self._controlword
            )
            try:
                self._download(d, ob.CONTROLWORD, 0, "H", cw)
                self._wait_state(d, lambda s: s not in POWERED, self.timeouts.state_s)
            except Exception as exc:
                self._event("error", d.node_id, None, f"disable failed: {exc}")
        self._event("info", None, None, "drives disabled")

    def close(self) -> None:
        """Disable the drives if needed, stop their PDOs (NMT pre-operational) and detach from
        the network (which the caller disconnects); never raises."""
        if self._closed:
            return
        try:
            if self._booted and (self._streaming or any(d.state in POWERED for d in self._drives)):
                self.disable()
            self._monitoring = False
            if self._booted and self.network.bus is not None:
                for d in self._drives:
                    try:
                        self._send(0x000, bytes([0x80, d.node_id]))
                    except Exception as exc:
                        self._event("error", d.node_id, None, f"NMT pre-operational failed: {exc}")
        finally:
            self._closed = True
            self._booted = False
            if self._gc_held:
                self._gc_held = False
                gcfreeze.release()
            notifier = self.network.notifier
            if notifier is not None and self._listener in notifier.listeners:
                notifier.remove_listener(self._listener)
            for d in self._drives:
                if self.network.nodes.get(d.node_id) is d.node:
                    try:
                        del self.network[d.node_id]
                    except Exception as exc:
                        logger.warning("drive master: removing node %d: %s", d.node_id, exc)

    def __enter__(self) -> Master:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- boot helpers --------------------------------------------------------------------------
    def _await(self, events: dict[int, threading.Event], what: str) -> None:
        deadline = time.monotonic() + self.timeouts.boot_s
        for d in self._drives:
            if not events[d.node_id].wait(max(0.0, deadline - time.monotonic())):
                raise DriveError(
                    f"{what} within {self.timeouts.boot_s} s",
                    node=d.node_id,
                    code=int(ob.EmcyCode.HEARTBEAT),
                )

    def _configure(self, d: _Drive) -> None:
        joint = self.robot.joints[d.joint]
        device_type = self._upload(d, ob.DEVICE_TYPE, 0, "I")
        if device_type & 0xFFFF != ob.PROFILE_402:
            raise DriveError(
                f"not a CiA 402 drive (device type 0x{device_type:08X})", node=d.node_id
            )
        if ob.SUPPORTED_MODES in self._od:
            modes = self._upload(d, ob.SUPPORTED_MODES, 0, "I")
            if not modes & ob.SUPPORTED_CSP_BIT:
                raise DriveError(
                    f"no cyclic synchronous position mode (0x6502 = 0x{modes:08X})",
                    node=d.node_id,
                )
        rated_ma = self._upload(d, ob.RATED_CURRENT, 0, "I")
        if rated_ma == 0:
            raise DriveError("motor rated current 0x6075 is 0", node=d.node_id)
        d.rated_a = rated_ma / 1000.0
        if abs(d.rated_a - joint.rated_current) > 0.01 * joint.rated_current:
            self._event(
                "warning",
                d.node_id,
                None,
                f"drive rated current {d.rated_a} A differs from the robot file "
                f"({joint.rated_current} A); the drive's value scales the currents",
            )
        if ob.ENCODER_RESOLUTION in self._od:
            increments = self._upload(d, ob.ENCODER_RESOLUTION, 1, "I")
            revolutions = self._upload(d, ob.ENCODER_RESOLUTION, 2, "I")
            if revolutions == 0 or increments != joint.encoder_counts * revolutions:
                raise ConfigError(
                    f"drive {d.node_id} reports {increments} counts per {revolutions} "
                    f"revolution(s), the robot file says {joint.encoder_counts}",
                    file=self.robot.source,
                    key=f"joint[{d.joint}].encoder_counts",
                )
        nid = d.node_id
        for k in range(1, 4):  # RPDO2..4 off
            if ob.RPDO_COMM + k in self._od:
                cob = 0x200 + 0x100 * k + nid
                self._download(d, ob.RPDO_COMM + k, 1, "I", ob.PDO_INVALID | cob)
        for k in range(2, 4):  # TPDO3..4 off
            if ob.TPDO_COMM + k in self._od:
                cob = 0x180 + 0x100 * k + nid
                self._download(d, ob.TPDO_COMM + k, 1, "I", ob.PDO_INVALID | cob)
        self._map_pdo(d, ob.RPDO_COMM, ob.RPDO_MAP, 0x200 + nid, self.layout.rpdo)
        self._map_pdo(d, ob.TPDO_COMM, ob.TPDO_MAP, 0x180 + nid, self.layout.tpdo1)
        self._map_pdo(d, ob.TPDO_COMM + 1, ob.TPDO_MAP + 1, 0x280 + nid, self.layout.tpdo2)
        if self._sync_counter:
            self._download(d, ob.SYNC_OVERFLOW, 0, "B", ob.SYNC_COUNTER_OVERFLOW)
        heartbeat_ms = round(self.timeouts.heartbeat_producer_s * 1000)
        self._download(d, ob.PRODUCER_HEARTBEAT, 0, "H", heartbeat_ms)
        value, index = self._interp
        self._download(d, ob.INTERPOLATION_PERIOD, 1, "B", value)
        self._download(d, ob.INTERPOLATION_PERIOD, 2, "b", index)
        self._download(d, ob.MODES_OF_OPERATION, 0, "b", ob.MODE_CSP)
        mode = self._upload(d, ob.MODES_DISPLAY, 0, "b")
        if mode != ob.MODE_CSP:
            raise DriveError(
                f"mode of operation display is {mode}, expected {ob.MODE_CSP} (CSP)",
                node=d.node_id,
            )

    def _map_pdo(
        self, d: _Drive, comm: int, mapping: int, cob: int, entries: tuple[ob.PdoEntry, ...]
    ) -> None:
        """Disable, set synchronous transmission, map, re-enable (CiA 301 §7.5.2.36)."""
        self._download(d, comm, 1, "I", ob.PDO_INVALID | cob)
        self._download(d, comm, 2, "B", 1)
        self._download(d, mapping, 0, "B", 0)
        for k, entry in enumerate(entries, start=1):
            self._download(d, mapping, k, "I", entry.mapping)
        self._download(d, mapping, 0, "B", len(entries))
        self._download(d, comm, 1, "I", cob)

    # --- CiA 402 helpers -----------------------------------------------------------------------
    def _read_state(self, d: _Drive) -> State:
        sw = self._upload(d, ob.STATUSWORD, 0, "H")
        try:
            state = decode_statusword(sw)
        except DriveError:
            raise DriveError(
                f"statusword 0x{sw:04X} shows no CiA 402 state", node=d.node_id, code=sw
            ) from None
        self._note_state(d, state)
        return state

    def _wait_state(self, d: _Drive, accept: object, timeout: float) -> State:
        """Poll the statusword until ``accept(state)``; return the last state read."""
        deadline = time.monotonic() + timeout
        while True:
            state = self._read_state(d)
            if accept(state) or time.monotonic() >= deadline:  # type: ignore[operator]
                return state
            time.sleep(self.timeouts.poll_s)

    def _walk(self, d: _Drive, goal: State, state: State | None = None) -> None:
        """Move a drive to ``goal`` one transition at a time, each within ``state_s``."""
        state = state if state is not None else self._read_state(d)
        resets = 0
        for _ in range(12):
            if state == goal:
                return
            cmd = command_towards(state, goal)
            before = state
            if cmd is None:  # transient state: the drive leaves it by itself
                state = self._wait_state(d, lambda s, b=before: s != b, self.timeouts.state_s)
            else:
                if before == State.FAULT:
                    if resets:
                        break
                    resets += 1
                    # Fault reset acts on the rising edge of bit 7: clear it first.
                    self._download(d, ob.CONTROLWORD, 0, "H", int(Command.DISABLE_VOLTAGE))
                self._download(d, ob.CONTROLWORD, 0, "H", cmd)
                state = self._wait_state(d, lambda s, b=before: s != b, self.timeouts.state_s)
            if state == before:
                raise DriveError(
                    f"no transition out of {before.name} towards {goal.name} "
                    f"within {self.timeouts.state_s} s",
                    node=d.node_id,
                    state=before.name,
                    code=self._error_code(d),
                )
        raise DriveError(
            f"cannot reach {goal.name} (stuck in {state.name})",
            node=d.node_id,
            state=state.name,
            code=self._error_code(d),
        )

    def _error_code(self, d: _Drive) -> int | None:
        """0x603F of a drive (None if it cannot be read or is 0)."""
        try:
            code = self._upload(d, ob.ERROR_CODE, 0, "H")
        except DriveError:
            return None
        return code or None

    # --- cyclic exchange -----------------------------------------------------------------------
    def _target_counts(self, target: np.ndarray) -> np.ndarray:
        q = np.asarray(target, dtype=float)
        if q.shape != (len(self._drives),) or not np.all(np.isfinite(q)):
            raise TrajectoryError(f"target must be {len(self._drives)} finite positions, got {q}")
        counts = np.rint((self._k @ q) * np.array([d.cpr for d in self._drives]))
        if np.any(np.abs(counts) >= 2**31):
            raise TrajectoryError("target outside the 32-bit encoder range")
        return counts.astype(np.int64)

    def _exchange(self, counts: np.ndarray) -> CycleSample:
        cycle = self._cycle
        counter = ob.sync_counter(cycle)
        n = len(self._drives)
        with self._lock:
            self._pending = counter
            self._frames = [[None, None] for _ in range(n)]
            self._missing = 2 * n
            self._complete.clear()
        cw = self._controlword
        for d in self._drives:
            self._send(0x200 + d.node_id, self._rpdo.pack(int(counts[d.joint]), cw))
        sync_ns = time.time_ns()
        t_sync = time.monotonic()
        self._send(0x80, bytes([counter]) if self._sync_counter else b"")
        complete = self._complete.wait(self.timeouts.tpdo_s)
        with self._lock:
            frames = self._frames
            self._pending = None
            last = self._last_arrival
        self._cycle += 1
        if not complete:
            self.check()  # a fault explains the silence better than the time-out
            for d in self._drives:
                for k in range(2):
                    if frames[d.joint][k] is None:
                        raise DriveError(
                            f"TPDO{k + 1} of cycle {cycle} missing {self.timeouts.tpdo_s} s "
                            f"after SYNC",
                            node=d.node_id,
                            state=d.state.name if d.state else None,
                            code=int(ob.EmcyCode.PDO_TIMEOUT),
                        )
        return self._decode(cycle, sync_ns, t_sync, counter, frames, counts, last - t_sync)

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
        raw: dict[str, list[int]] = {
            name: []
            for name in (
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
        }
        for d in self._drives:
            values: dict[str, int] = {"sync_counter": counter}
            for k, entries in enumerate(self.layout.tpdos):
                data = frames[d.joint][k]
                assert data is not None
                values.update({e.name: int(v) for e, v in zip(entries, data, strict=True)})
            values["target"] = int(counts[d.joint])
            for name, column in raw.items():
                column.append(values[name])
        rated = np.array([d.rated_a for d in self._drives])
        position = self._joint_positions(np.array(raw["position"], dtype=float))
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

    def _check_sample(self, sample: CycleSample) -> None:
        states = []
        for d, sw in zip(self._drives, sample.raw["statusword"], strict=True):
            try:
                state = decode_statusword(sw)
            except DriveError:
                raise DriveError(
                    f"statusword 0x{sw:04X} shows no CiA 402 state", node=d.node_id, code=sw
                ) from None
            self._note_state(d, state)
            states.append(state)
        self.check()
        for d, state, mode in zip(self._drives, states, sample.raw["mode"], strict=True):
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                raise DriveError(
                    "drive in fault", node=d.node_id, state=state.name, code=self._error_code(d)
                )
            if state != State.OPERATION_ENABLED:
                raise DriveError(
                    "drive left OPERATION_ENABLED",
                    node=d.node_id,
                    state=state.name,
                    code=self._error_code(d),
                )
            if mode != ob.MODE_CSP:
                raise DriveError(
                    f"drive left cyclic synchronous position mode (mode {mode})",
                    node=d.node_id,
                    state=state.name,
                )

    def _joint_positions(self, counts: np.ndarray) -> np.ndarray:
        motor = counts / np.array([d.cpr for d in self._drives])
        return self._kinv @ motor

    # --- reception (notifier thread) -----------------------------------------------------------
    def _on_frame(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self._on_error_frame(msg)
            return
        if msg.is_remote_frame:
            return
        cob = msg.arbitration_id
        hit = self._tpdo_index.get(cob)
        if hit is not None:
            self._on_tpdo(hit[0], hit[1], bytes(msg.data))
            return
        node_id = cob & 0x7F
        d = self._by_node.get(node_id)
        if d is None:
            return
        function = cob & 0x780
        if function == 0x700 and msg.dlc >= 1:
            self._on_heartbeat(d, msg.data[0] & 0x7F)
        elif function == 0x080 and node_id != 0:
            self._on_emcy(d, bytes(msg.data))

    def _on_tpdo(self, d: _Drive, k: int, data: bytes) -> None:
        layout = self._tpdo_structs[k]
        if len(data) < layout.size:
            self._add_fault(
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
                    self._events.append(
                        DriveEvent(
                            time.time_ns(),
                            "warning",
                            d.node_id,
                            None,
                            f"TPDO{k + 1} of SYNC {echo} arrived during SYNC {pending}: dropped",
                        )
                    )
                    return
            slot = self._frames[d.joint]
            if slot[k] is None:
                self._missing -= 1
            slot[k] = values
            if self._missing == 0:
                self._last_arrival = time.monotonic()
                self._complete.set()

    def _on_heartbeat(self, d: _Drive, state: int) -> None:
        d.last_heartbeat = time.monotonic()
        previous, d.nmt = d.nmt, state
        if state == 0:
            self._bootup[d.node_id].set()
        if state == _NMT_OPERATIONAL:
            self._operational[d.node_id].set()
        if state != previous:
            name = _NMT_NAMES.get(state, f"0x{state:02X}")
            level = "info"
            if self._monitoring and state != _NMT_OPERATIONAL:
                level = "error"
                self._add_fault(
                    DriveError(
                        f"node left OPERATIONAL (NMT {name})",
                        node=d.node_id,
                        code=int(ob.EmcyCode.HEARTBEAT),
                    )
                )
            self._event(level, d.node_id, None, f"NMT {name}")

    def _on_emcy(self, d: _Drive, data: bytes) -> None:
        if len(data) < 2:
            return
        code = int.from_bytes(data[0:2], "little")
        register = data[2] if len(data) > 2 else 0
        if code == 0:
            self._event("info", d.node_id, 0, "EMCY error reset")
            return
        text = f"EMCY 0x{code:04X} (error register 0x{register:02X})"
        self._event("error", d.node_id, code, text)
        self._add_fault(DriveError(text, node=d.node_id, code=code))

    def _on_error_frame(self, msg: can.Message) -> None:
        cls = msg.arbitration_id
        data = bytes(msg.data)
        if cls & _ERR_BUSOFF:
            self._event("error", None, int(ob.EmcyCode.BUS_OFF), "CAN bus-off")
            self._add_fault(BusError("CAN bus-off", code=int(ob.EmcyCode.BUS_OFF)))
            return
        if cls & _ERR_CRTL and len(data) > 1 and data[1] & _ERR_CRTL_PASSIVE:
            self._event("error", None, int(ob.EmcyCode.CAN_ERROR_PASSIVE), "CAN error passive")
            self._add_fault(
                BusError("CAN controller error passive", code=int(ob.EmcyCode.CAN_ERROR_PASSIVE))
            )
            return
        now = time.monotonic()
        self._error_frames.append(now)
        self._event("warning", None, None, f"CAN error frame (class 0x{cls:X})")
        if len(self._error_frames) > ERROR_FRAMES_PER_S and now - self._error_frames[0] < 1.0:
            self._error_frames.clear()
            self._add_fault(
                BusError(
                    f"more than {ERROR_FRAMES_PER_S} CAN error frames per second",
                    code=int(ob.EmcyCode.CAN_OVERRUN),
                )
            )

    # --- small helpers -------------------------------------------------------------------------
    def _add_fault(self, fault: DriveError) -> None:
        with self._lock:
            self._faults.append(fault)

    def _event(self, level: str, node: int | None, code: int | None, text: str) -> None:
        self._events.append(DriveEvent(time.time_ns(), level, node, code, text))

    def _note_state(self, d: _Drive, state: State) -> None:
        if state != d.state:
            old = d.state.name if d.state else "unknown"
            level = "error" if state in (State.FAULT, State.FAULT_REACTION_ACTIVE) else "info"
            self._event(level, d.node_id, None, f"CiA 402 {old} -> {state.name}")
            d.state = state

    def _check_heartbeats(self) -> None:
        now = time.monotonic()
        limit = self.timeouts.heartbeat_s
        for d in self._drives:
            if d.last_heartbeat is None or now - max(d.last_heartbeat, d.silence_reported) <= limit:
                continue
            silent = now - d.last_heartbeat
            d.silence_reported = now  # one error per time-out period of silence
            self._add_fault(
                DriveError(
                    f"no heartbeat for {silent:.3f} s (limit {limit} s)",
                    node=d.node_id,
                    code=int(ob.EmcyCode.HEARTBEAT),
                )
            )

    def _alive(self, d: _Drive) -> bool:
        """False for a drive whose heartbeat stopped: on the way down, do not wait for SDO
        answers that cannot come."""
        if (
            d.last_heartbeat is None
            or time.monotonic() - d.last_heartbeat <= self.timeouts.heartbeat_s
        ):
            return True
        self._event("warning", d.node_id, None, "no heartbeat: drive skipped")
        return False

    def _require_booted(self) -> None:
        if self._closed:
            raise DriveError("the master is closed")
        if not self._booted:
            raise DriveError("the drives are not booted (call boot() first)")

    def _check_bus(self) -> None:
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

    def _send(self, cob: int, data: bytes) -> None:
        try:
            self.network.send_message(cob, data)
        except (can.CanError, OSError) as exc:
            raise BusError(f"cannot send frame 0x{cob:03X}: {exc}") from None
        except Exception as exc:  # network.check() re-raises the reader thread's failure
            raise BusError(f"CAN bus failed: {exc}") from None

    @contextlib.contextmanager
    def _sdo_errors(self, d: _Drive, what: str) -> Iterator[None]:
        """Map canopen/python-can SDO failures of ``what`` (e.g. "write 0x6060:00 = 8") to the
        drivegain error tree, with the node id and the abort code."""
        try:
            yield
        except SdoAbortedError as exc:
            raise DriveError(f"SDO {what} refused ({exc})", node=d.node_id, code=exc.code) from None
        except SdoCommunicationError as exc:
            raise DriveError(
                f"no SDO answer to {what} ({exc})",
                node=d.node_id,
                code=int(ob.EmcyCode.SDO_TIMEOUT),
            ) from None
        except (can.CanError, OSError) as exc:
            raise BusError(f"SDO {what} on node {d.node_id} failed: {exc}") from None

    def _download(self, d: _Drive, index: int, subindex: int, fmt: str, value: int) -> None:
        with self._sdo_errors(d, f"write 0x{index:04X}:{subindex:02X} = {value}"):
            d.node.sdo.download(index, subindex, struct.pack("<" + fmt, value))

    def _upload(self, d: _Drive, index: int, subindex: int, fmt: str) -> int:
        size = struct.calcsize("<" + fmt)
        with self._sdo_errors(d, f"read 0x{index:04X}:{subindex:02X}"):
            data = d.node.sdo.upload(index, subindex)
        if len(data) < size:
            raise DriveError(
                f"SDO read 0x{index:04X}:{subindex:02X} returned {len(data)} bytes, "
                f"expected {size}",
                node=d.node_id,
            )
        return int(struct.unpack_from("<" + fmt, data)[0])
