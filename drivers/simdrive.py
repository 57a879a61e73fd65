"""One simulated CiA 402 servo drive: a canopen LocalNode with the behaviour of a real drive.

canopen's LocalNode answers SDO from its object dictionary and nothing more. This module adds what
a drive does: NMT (boot-up, reset, start/stop, no SDO while stopped), a heartbeat producer (driven
by the cell's clock), a heartbeat consumer of the master (0x1016, :mod:`.simclock`) with its fault
reaction, PDO mapping checks on SDO writes, RPDOs applied at the next SYNC,
TPDOs sent on SYNC (before the RPDO data is applied), the CiA 402 state machine driven by the
controlword, fault and EMCY production. Physics and time live in :mod:`drivegain.drivers.sim`,
which calls :meth:`begin_sync`, :meth:`tpdo_frames` and :meth:`latch` at each SYNC.

Every bus callback runs in the simulated bus's notifier thread (in lockstep on the virtual bus: in
the sender's thread, :mod:`.simtime`) and is wrapped by the cell's guard (a failing
callback would silently skip the other callbacks of the same CAN id).
"""

from __future__ import annotations

import struct
from enum import IntEnum
from typing import TYPE_CHECKING, Any

import canopen
from canopen import objectdictionary as odmod
from canopen.sdo import SdoAbortedError

from drivegain.drivers import objects as ob
from drivegain.drivers.cia402 import (
    SW_FOLLOWING,
    SW_FOLLOWING_ERROR,
    SW_REMOTE,
    State,
    apply_controlword,
    encode_statusword,
)
from drivegain.drivers.physics import MotorMode
from drivegain.drivers.simclock import HeartbeatConsumer

if TYPE_CHECKING:
    from drivegain.drivers.sim import SimulatedCell

# SDO abort codes (CiA 301).
ABORT_VALUE_RANGE = 0x0609_0030
ABORT_VALUE_TOO_HIGH = 0x0609_0031
ABORT_NOT_MAPPABLE = 0x0604_0041
ABORT_PDO_TOO_LONG = 0x0604_0042
ABORT_INCOMPATIBLE = 0x0604_0043
ABORT_DEVICE_STATE = 0x0800_0022

_SIGNED = {odmod.INTEGER8: "b", odmod.INTEGER16: "h", odmod.INTEGER32: "i"}
_UNSIGNED = {odmod.UNSIGNED8: "B", odmod.UNSIGNED16: "H", odmod.UNSIGNED32: "I"}


class NmtState(IntEnum):
    """NMT states with their heartbeat byte."""

    INITIALISING = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


class DriveNode(canopen.LocalNode):
    """LocalNode whose NMT and SDO services are routed through the simulated drive."""

    def __init__(self, node_id: int, od: odmod.ObjectDictionary, drive: SimDrive):
        super().__init__(node_id, od)
        # The drive produces heartbeats from the cell's timer thread, not one python-can
        # periodic task (thread) per node.
        self._write_callbacks.remove(self.nmt.on_write)
        self.drive = drive

    def associate_network(self, network: canopen.Network) -> None:
        super().associate_network(network)
        network.unsubscribe(self.sdo.rx_cobid, self.sdo.on_request)
        network.unsubscribe(0, self.nmt.on_command)
        network.subscribe(self.sdo.rx_cobid, self.drive.on_sdo_request)
        network.subscribe(0, self.drive.on_nmt)

    def remove_network(self) -> None:
        if not self.has_network():
            return
        self.network.unsubscribe(self.sdo.rx_cobid, self.drive.on_sdo_request)
        self.network.unsubscribe(0, self.drive.on_nmt)
        self.network.subscribe(self.sdo.rx_cobid, self.sdo.on_request)
        self.network.subscribe(0, self.nmt.on_command)
        super().remove_network()


class SimDrive:
    """A simulated drive on joint ``joint`` of the cell.

    Parameters
    ----------
    cell
        The owning cell (physics, timer, guard).
    joint
        0-based joint (= motor) index.
    node_id
        CANopen node id.
    od
        This node's object dictionary (from the EDS).
    commissioning
        (index, subindex) -> value set at power-on, kept over NMT resets (the drive's stored
        parameters: rated current, encoder resolution, following error window, ...).
    """

    def __init__(
        self,
        cell: SimulatedCell,
        joint: int,
        node_id: int,
        od: odmod.ObjectDictionary,
        commissioning: dict[tuple[int, int], int],
    ):
        self.cell = cell
        self.joint = joint
        self.node_id = node_id
        self.od = od
        self.commissioning = dict(commissioning)
        self.node = DriveNode(node_id, od, self)
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        self.nmt = NmtState.INITIALISING
        self.state = State.NOT_READY_TO_SWITCH_ON
        self.controlword = 0
        self.error_code = 0
        self.error_register = 0
        self.mode = 0
        self.sync_echo = 0
        self.sample: dict[int, int] = {}
        self.rpdos: list[ob.ActivePdo] = []
        self.tpdos: list[ob.ActivePdo] = []
        self._pdo_dirty = True
        self._subscribed: list[int] = []
        self._rpdo_pending: dict[tuple[int, int], int] = {}
        # Fault injection switches.
        self.never_boots = False
        self.heartbeat_stopped = False
        self.tpdo_dropped: set[int] = set()
        self.tpdo_delay: dict[int, float] = {}
        # Heartbeat producer (read by the timer thread).
        self.heartbeat_period_s = 0.0
        self.heartbeat_generation = 0
        self._fe_since: float | None = None  # following error beyond the window since (s)
        # stored_int: (index, subindex) -> (the stored bytes decoded, their value)
        self._decoded: dict[tuple[int, int], tuple[bytes, int]] = {}
        self.consumer = HeartbeatConsumer(self, cell.clock)
        self._ramp_reaction = False  # the fault reaction ramps the motor to rest
        self._apply_commissioning()

    # --- object dictionary --------------------------------------------------------------------
    def _var(self, index: int, subindex: int) -> odmod.ODVariable:
        obj = self.od[index]
        if isinstance(obj, odmod.ODVariable):
            return obj
        return obj[subindex]

    def stored(self, index: int, subindex: int = 0) -> Any:
        """Value of an object as stored (or its EDS default)."""
        return self._var(index, subindex).decode_raw(self.node.get_data(index, subindex))

    def stored_int(self, index: int, subindex: int = 0) -> int:
        """``int(stored(index, subindex))`` of an object the drive does not compute (see
        :meth:`_live`), decoded once per value stored: read at every SYNC."""
        raw = self.node.data_store.get(index, {}).get(subindex)
        key = (index, subindex)
        hit = self._decoded.get(key)
        if raw is not None and hit is not None and hit[0] is raw:
            return hit[1]
        value = int(self.stored(index, subindex))
        if raw is not None:  # (an EDS default is decoded each time: no value to compare)
            self._decoded[key] = (raw, value)
        return value

    def _store(self, index: int, subindex: int, value: int) -> None:
        raw = bytes(self._var(index, subindex).encode_raw(value))
        self.node.data_store.setdefault(index, {})[subindex] = raw
        if type(value) is int:  # what decoding ``raw`` gives: an integer decodes to itself
            self._decoded[(index, subindex)] = (raw, value)

    def _apply_commissioning(self) -> None:
        for (index, subindex), value in self.commissioning.items():
            self._store(index, subindex, value)
        self.rated_ma = int(self.stored(ob.RATED_CURRENT))

    def _on_read(self, index: int, subindex: int, od: odmod.ODVariable) -> int | None:
        return self._live(index)

    def _live(self, index: int) -> int | None:
        """Values the drive computes (state, measurements); ``None`` for stored objects."""
        if index == ob.STATUSWORD:
            return self.statusword()
        if index == ob.MODES_DISPLAY:
            return self.mode if self.mode in (0, ob.MODE_CSP) else 0
        if index == ob.ERROR_CODE:
            return self.error_code
        if index == ob.ERROR_REGISTER:
            return self.error_register
        if index == ob.CONTROLWORD:
            return self.controlword
        if index == ob.SYNC_ECHO:
            return self.sync_echo
        if index in self.sample:
            return self.sample[index]
        return None

    def statusword(self) -> int:
        extra = SW_REMOTE
        if self.state == State.OPERATION_ENABLED and self.mode == ob.MODE_CSP:
            extra |= SW_FOLLOWING
        if self._fe_since is not None:
            extra |= SW_FOLLOWING_ERROR
        return encode_statusword(self.state, extra)

    def _on_write(self, index: int, subindex: int, od: odmod.ODVariable, data: bytes) -> None:
        value = od.decode_raw(data)
        if index == ob.CONTROLWORD:
            self.apply_controlword(int(value))
        elif index == ob.MODES_OF_OPERATION:
            if value not in (0, ob.MODE_CSP):
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            self.mode = int(value)
            self._update_motor()
        elif index == ob.PRODUCER_HEARTBEAT:
            self.cell.set_heartbeat(self, int(value) / 1000.0)
        elif index == ob.CONSUMER_HEARTBEAT:
            self.consumer.configure(int(value))
            self.cell.watch_producer(self.consumer.producer)
        elif index == ob.SYNC_OVERFLOW:
            if ob.COMM_CYCLE_PERIOD in self.od and self.stored(ob.COMM_CYCLE_PERIOD) != 0:
                raise SdoAbortedError(ABORT_DEVICE_STATE)
            if not isinstance(value, int) or value == 1 or value > ob.SYNC_COUNTER_OVERFLOW:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
        elif index == ob.RATED_CURRENT:
            if value == 0:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            self.rated_ma = int(value)
        elif ob.RPDO_COMM <= index < ob.RPDO_COMM + 4 or ob.TPDO_COMM <= index < ob.TPDO_COMM + 4:
            self._check_comm_write(index, subindex, int(value))
        elif ob.RPDO_MAP <= index < ob.RPDO_MAP + 4 or ob.TPDO_MAP <= index < ob.TPDO_MAP + 4:
            self._check_map_write(index, subindex, int(value))

    # --- PDO configuration ---------------------------------------------------------------------
    def _comm_of(self, map_index: int) -> int:
        return map_index - 0x200  # 0x1600 -> 0x1400, 0x1A00 -> 0x1800

    def _check_comm_write(self, index: int, subindex: int, value: int) -> None:
        current = int(self.stored(index, 1))
        if subindex == 1:
            both_valid = not current & ob.PDO_INVALID and not value & ob.PDO_INVALID
            if both_valid and (current & 0x7FF) != (value & 0x7FF):
                raise SdoAbortedError(ABORT_VALUE_RANGE)
        elif subindex == 2 and 241 <= value <= 251:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        self._pdo_dirty = True

    def _mapped(self, value: int) -> ob.MappedEntry:
        index, subindex, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
        try:
            var = self._var(index, subindex)
        except KeyError:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE) from None
        if not var.pdo_mappable:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        dtype = var.data_type
        fmt = None if dtype is None else _SIGNED.get(dtype) or _UNSIGNED.get(dtype)
        if fmt is None:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        if struct.calcsize("<" + fmt) * 8 != bits:
            raise SdoAbortedError(ABORT_INCOMPATIBLE)
        return ob.MappedEntry.of(index, subindex, fmt)

    def _check_map_write(self, index: int, subindex: int, value: int) -> None:
        cob = int(self.stored(self._comm_of(index), 1))
        if not cob & ob.PDO_INVALID:
            raise SdoAbortedError(ABORT_DEVICE_STATE)
        if subindex == 0:
            if value > 8:
                raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
            entries = [self._mapped(int(self.stored(index, k))) for k in range(1, value + 1)]
            if sum(e.bits for e in entries) > 64:
                raise SdoAbortedError(ABORT_PDO_TOO_LONG)
        else:
            if int(self.stored(index, 0)) != 0:
                raise SdoAbortedError(ABORT_DEVICE_STATE)
            self._mapped(value)
        self._pdo_dirty = True

    def _read_pdos(self, comm_base: int, map_base: int) -> list[ob.ActivePdo]:
        active = []
        for k in range(4):
            if comm_base + k not in self.od:
                continue
            cob = int(self.stored(comm_base + k, 1))
            if cob & ob.PDO_INVALID:
                continue
            count = int(self.stored(map_base + k, 0))
            entries = tuple(
                self._mapped(int(self.stored(map_base + k, s))) for s in range(1, count + 1)
            )
            packer = struct.Struct("<" + "".join(e.fmt for e in entries))
            trans = int(self.stored(comm_base + k, 2))
            active.append(ob.ActivePdo(k + 1, cob & 0x7FF, trans, entries, packer))
        return active

    def _activate_pdos(self) -> None:
        self._deactivate_pdos()
        self.rpdos = self._read_pdos(ob.RPDO_COMM, ob.RPDO_MAP)
        self.tpdos = self._read_pdos(ob.TPDO_COMM, ob.TPDO_MAP)
        network = self.node.network
        for pdo in self.rpdos:
            network.subscribe(pdo.cob_id, self.on_rpdo)
            self._subscribed.append(pdo.cob_id)
        self._pdo_dirty = False

    def _deactivate_pdos(self) -> None:
        for cob in self._subscribed:
            self.node.network.unsubscribe(cob, self.on_rpdo)
        self._subscribed = []
        self.rpdos, self.tpdos = [], []
        self._rpdo_pending = {}

    # --- bus callbacks -------------------------------------------------------------------------
    def on_sdo_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.never_boots or self.nmt not in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL):
            return
        self.cell.guard(self.node.sdo.on_request, can_id, data, timestamp)

    def on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.cell.guard(self._nmt, bytes(data))

    def _nmt(self, data: bytes) -> None:
        if self.never_boots or len(data) < 2 or data[1] not in (0, self.node_id):
            return
        cs = data[0]
        if cs == 0x01:
            self._enter(NmtState.OPERATIONAL)
        elif cs == 0x02:
            self._enter(NmtState.STOPPED)
        elif cs == 0x80:
            self._enter(NmtState.PRE_OPERATIONAL)
        elif cs in (0x81, 0x82):
            self.reset(application=cs == 0x81)

    def _enter(self, state: NmtState) -> None:
        if self.nmt == NmtState.INITIALISING:
            return
        if state == NmtState.OPERATIONAL:
            self._activate_pdos()
            for pdo in self.tpdos:
                pdo.sync_count = 0
        elif self.nmt == NmtState.OPERATIONAL:
            self._deactivate_pdos()
        self.nmt = state

    def reset(self, *, application: bool) -> None:
        """NMT reset (communication, or the whole node) then boot-up into PRE-OPERATIONAL."""
        self._deactivate_pdos()
        self.nmt = NmtState.INITIALISING
        store = self.node.data_store
        for index in list(store):
            if application or index < 0x2000:
                del store[index]
        self._apply_commissioning()
        if ob.CONSUMER_HEARTBEAT in self.od:  # back to its default with the communication objects
            self.consumer.configure(int(self.stored(ob.CONSUMER_HEARTBEAT, 1)))
        if application:
            self.controlword = 0
            self.mode = 0
            self.error_code = 0
            self.error_register = 0
            self._set_state(State.SWITCH_ON_DISABLED)
        self.cell.set_heartbeat(self, int(self.stored(ob.PRODUCER_HEARTBEAT)) / 1000.0)
        self.boot()

    def boot(self) -> None:
        """Send the boot-up message and enter PRE-OPERATIONAL (the node's power-on)."""
        if self.never_boots:
            return
        if self.state == State.NOT_READY_TO_SWITCH_ON:
            self._set_state(State.SWITCH_ON_DISABLED)
        self.node.network.send_message(0x700 + self.node_id, bytes([0]))
        self.nmt = NmtState.PRE_OPERATIONAL

    def on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.cell.guard(self._rpdo, can_id, bytes(data))

    def _rpdo(self, can_id: int, data: bytes) -> None:
        if self.nmt != NmtState.OPERATIONAL:
            return
        for pdo in self.rpdos:
            if pdo.cob_id != can_id:
                continue
            if len(data) < pdo.packer.size:
                self.send_emcy(0x8210)  # PDO not processed due to length error
                return
            decoded = dict(zip(pdo.keys, pdo.packer.unpack_from(data), strict=True))
            if pdo.trans_type <= 240:
                self._rpdo_pending.update(decoded)
            else:
                self._apply_rpdo(decoded)

    def _apply_rpdo(self, values: dict[tuple[int, int], int]) -> None:
        for (index, subindex), value in values.items():
            if index == ob.CONTROLWORD:
                continue
            if index < 0x1000:  # dummy mapping
                continue
            self._store(index, subindex, value)
        cw = values.get((ob.CONTROLWORD, 0))
        if cw is not None:
            self.apply_controlword(int(cw))

    # --- CiA 402 -----------------------------------------------------------------------------
    def apply_controlword(self, cw: int) -> None:
        new = apply_controlword(self.state, cw, self.controlword)
        self.controlword = cw
        if new != self.state:
            if self.state == State.FAULT:
                self._clear_fault()
            self._set_state(new)

    def apply_quick_stop_end(self) -> None:
        """The quick stop ramp reached rest: quick stop option code 2 switches the drive off; a
        fault reaction ends in FAULT (brake)."""
        if self.state == State.QUICK_STOP_ACTIVE:
            self._set_state(State.SWITCH_ON_DISABLED)
        elif self.state == State.FAULT_REACTION_ACTIVE and self._ramp_reaction:
            self._ramp_reaction = False
            self._set_state(State.FAULT)

    def on_producer_heartbeat(self, sent: float) -> None:
        """A heartbeat of the producer the consumer watches, sent at ``sent`` (cell's clock)."""
        if not self.never_boots and self.nmt != NmtState.INITIALISING:
            self.consumer.on_heartbeat(sent)

    def _set_state(self, state: State) -> None:
        self.state = state
        self._update_motor()

    def _update_motor(self) -> None:
        if self.state == State.OPERATION_ENABLED:
            mode = MotorMode.TRACK
        elif self.state == State.QUICK_STOP_ACTIVE or (
            self.state == State.FAULT_REACTION_ACTIVE and self._ramp_reaction
        ):
            mode = MotorMode.QUICK_STOP
        else:
            mode = MotorMode.BRAKED
        self.cell.physics.set_mode(self.joint, mode)

    @property
    def tracking(self) -> bool:
        """Follows CSP targets (operation enabled in cyclic synchronous position mode)."""
        return self.state == State.OPERATION_ENABLED and self.mode == ob.MODE_CSP

    def inject_fault(self, code: int, *, emcy: bool, ramp: bool = False) -> None:
        """Fault reaction then FAULT, with ``code`` in 0x603F (and an EMCY if ``emcy``).

        ``ramp``: a powered motor first ramps to rest with the quick stop deceleration (0x6085),
        as for a lost heartbeat; otherwise the reaction is "disable drive function" (the brake
        holds at once).
        """
        if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return
        self.error_code = code
        self.error_register = ob.error_register_for(code)
        self._push_error_history(code)
        self._ramp_reaction = ramp and self.state in (
            State.OPERATION_ENABLED,
            State.QUICK_STOP_ACTIVE,
        )
        self._set_state(State.FAULT_REACTION_ACTIVE)
        if emcy:
            self.send_emcy(code)
        if self._ramp_reaction:
            self.cell.watch_ramps()  # FAULT when the ramp ends (apply_quick_stop_end)
        else:
            self._set_state(State.FAULT)

    def _push_error_history(self, code: int) -> None:
        if ob.ERROR_HISTORY not in self.od:
            return
        depth = len(self.od[ob.ERROR_HISTORY]) - 1
        count = int(self.stored(ob.ERROR_HISTORY, 0))
        for k in range(min(count, depth - 1), 0, -1):
            self._store(ob.ERROR_HISTORY, k + 1, int(self.stored(ob.ERROR_HISTORY, k)))
        self._store(ob.ERROR_HISTORY, 1, code)
        self._store(ob.ERROR_HISTORY, 0, min(count + 1, depth))

    def _clear_fault(self) -> None:
        had = self.error_register
        self.error_code = 0
        self.error_register = 0
        self._fe_since = None
        if had:
            self.send_emcy(0x0000)  # error reset

    def send_emcy(self, code: int) -> None:
        register = self.error_register if code else 0
        self.node.emcy.send(code, register, b"\x00" * 5)

    def check_following_error(self, error_counts: int, now_s: float) -> None:
        """Monitor 0x6065 / 0x6066: fault 0x8611 when the error stays beyond the window."""
        window = self.stored_int(ob.FOLLOWING_ERROR_WINDOW)
        if window == 0xFFFFFFFF or not self.tracking or abs(error_counts) <= window:
            self._fe_since = None
            return
        if self._fe_since is None:
            self._fe_since = now_s
        timeout = self.stored_int(ob.FOLLOWING_ERROR_TIMEOUT) / 1000.0
        if now_s - self._fe_since >= timeout:
            self.inject_fault(int(ob.EmcyCode.FOLLOWING_ERROR), emcy=True)

    # --- SYNC ----------------------------------------------------------------------------------
    def begin_sync(self, counter: int) -> None:
        """The SYNC instant, before the TPDOs go out: echo its counter, take a new PDO mapping
        into use."""
        self.sync_echo = counter
        if self.nmt == NmtState.OPERATIONAL and self._pdo_dirty:
            self._activate_pdos()

    def latch(self) -> int | None:
        """Apply the synchronous RPDO data received before this SYNC; return the CSP target
        (counts) if the drive follows targets.

        Called after this SYNC's TPDOs went out, as a drive that transmits the values it sampled
        at the SYNC at once and runs its control update afterwards: a controlword's effect shows
        in the statusword of the next SYNC.
        """
        if self.nmt != NmtState.OPERATIONAL:
            return None
        if self._rpdo_pending:
            pending, self._rpdo_pending = self._rpdo_pending, {}
            self._apply_rpdo(pending)
        if not self.tracking:
            return None
        return self.stored_int(ob.TARGET_POSITION)

    def tpdo_frames(self) -> list[tuple[int, int, bytes]]:
        """(TPDO number, COB-ID, data) of the TPDOs due at this SYNC."""
        if self.nmt != NmtState.OPERATIONAL:
            return []
        live = self.live_values()
        frames = []
        for pdo in self.tpdos:
            if not 1 <= pdo.trans_type <= 240:
                continue  # acyclic / event-driven TPDOs are not produced here
            pdo.sync_count += 1
            if pdo.sync_count % pdo.trans_type:
                continue
            values = []
            for e in pdo.entries:
                v = live[e.index] if e.index in live else int(self.stored(e.index, e.subindex))
                values.append(v if e.lo <= v <= e.hi else e.fit(v))
            frames.append((pdo.number, pdo.cob_id, pdo.packer.pack(*values)))
        return frames

    def live_values(self) -> dict[int, int]:
        """Every value the drive computes (see :meth:`_live`), by index."""
        return {
            **self.sample,
            ob.STATUSWORD: self.statusword(),
            ob.MODES_DISPLAY: self._live(ob.MODES_DISPLAY) or 0,
            ob.ERROR_CODE: self.error_code,
            ob.ERROR_REGISTER: self.error_register,
            ob.CONTROLWORD: self.controlword,
            ob.SYNC_ECHO: self.sync_echo,
        }
