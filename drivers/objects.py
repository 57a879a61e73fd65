"""Object dictionary entries, PDO layouts and error codes shared by master and simulated drives.

Indexes are those of CiA 301 (communication) and CiA 402 (drive profile). One manufacturer object
is ours: 0x2010, the counter byte of the last SYNC, echoed in every TPDO so that the master tags
samples by SYNC counter (a drive whose EDS lacks it gets a layout without the echo, and the master
tags by arrival window instead).
"""

from __future__ import annotations

import copy
import functools
import math
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path

from canopen.objectdictionary import ObjectDictionary, ODVariable, import_od

from drivegain.config import resource_path
from drivegain.errors import ConfigError

# --- CiA 301 -----------------------------------------------------------------------------------
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
ERROR_HISTORY = 0x1003
COB_ID_SYNC = 0x1005
COMM_CYCLE_PERIOD = 0x1006
CONSUMER_HEARTBEAT = 0x1016
PRODUCER_HEARTBEAT = 0x1017
SYNC_OVERFLOW = 0x1019
RPDO_COMM = 0x1400
RPDO_MAP = 0x1600
TPDO_COMM = 0x1800
TPDO_MAP = 0x1A00
# --- manufacturer ------------------------------------------------------------------------------
SYNC_ECHO = 0x2010
# --- CiA 402 -----------------------------------------------------------------------------------
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
POSITION_DEMAND = 0x6062
POSITION_ACTUAL = 0x6064
FOLLOWING_ERROR_WINDOW = 0x6065
FOLLOWING_ERROR_TIMEOUT = 0x6066
VELOCITY_ACTUAL = 0x606C
MAX_CURRENT = 0x6073
TORQUE_DEMAND = 0x6074
RATED_CURRENT = 0x6075
RATED_TORQUE = 0x6076
TORQUE_ACTUAL = 0x6077
CURRENT_ACTUAL = 0x6078
TARGET_POSITION = 0x607A
QUICK_STOP_DECELERATION = 0x6085
ENCODER_RESOLUTION = 0x608F
INTERPOLATION_PERIOD = 0x60C2
FOLLOWING_ERROR_ACTUAL = 0x60F4
SUPPORTED_MODES = 0x6502

#: Device type 0x1000, low 16 bits: the device profile number.
PROFILE_402 = 402
#: 0x6060 value of cyclic synchronous position mode.
MODE_CSP = 8
#: 0x6502 bit of cyclic synchronous position mode.
SUPPORTED_CSP_BIT = 1 << 7
#: SYNC counter overflow value (0x1019): the counter byte runs 1..240.
SYNC_COUNTER_OVERFLOW = 240

#: PDO COB-ID flag: PDO not valid.
PDO_INVALID = 0x8000_0000


def default_eds() -> Path:
    """The shipped EDS of the simulated CiA 402 servo drive."""
    return resource_path("cia402-servo.eds")


@functools.lru_cache(maxsize=8)
def _parsed_od(path: str, mtime_ns: int, size: int) -> ObjectDictionary:
    """``path`` parsed with node id 0: ``$NODEID`` values hold their offset only."""
    return import_od(path, 0)


def _variables(od: ObjectDictionary) -> Iterator[ODVariable]:
    for obj in od.values():
        if isinstance(obj, ODVariable):
            yield obj
        else:
            yield from obj.values()


def load_od(eds: Path | str, node_id: int) -> ObjectDictionary:
    """The object dictionary of ``eds`` for node ``node_id``, as canopen's ``import_od`` gives it.

    A master and its simulated drives need one dictionary per node and side; parsing the EDS
    (configparser) for each took most of their start-up. The file is parsed once (again when it
    changes) and each node gets its own deep copy, with the ``$NODEID`` values of this node.

    Raises
    ------
    Exception
        Whatever canopen raises for an unreadable EDS, or ``OSError``.
    """
    path = os.fspath(eds)
    st = os.stat(path)
    od = copy.deepcopy(_parsed_od(path, st.st_mtime_ns, st.st_size))
    if od.node_id is not None:  # from the EDS's [DeviceComissioning]: as canopen sets it
        od.node_id = node_id
    for var in _variables(od):
        # canopen resolves "$NODEID+0x180" to 0x180 + node id (offset: parsed with node id 0)
        if "$NODEID" in (getattr(var, "default_raw", None) or "") and isinstance(var.default, int):
            var.default += node_id
        if "$NODEID" in (getattr(var, "value_raw", None) or "") and isinstance(var.value, int):
            var.value += node_id
    return od


def sync_counter(cycle: int) -> int:
    """SYNC counter byte of cycle ``cycle`` (0-based): 1..240, as CiA 301 counts."""
    return cycle % SYNC_COUNTER_OVERFLOW + 1


class EmcyCode(IntEnum):
    """Error codes (CiA 301 / 402 EMCY codes) the master and the simulator use."""

    GENERIC = 0x1000
    CONTINUOUS_OVERCURRENT = 0x2310
    CAN_OVERRUN = 0x8110
    CAN_ERROR_PASSIVE = 0x8120
    HEARTBEAT = 0x8130  # life guard / heartbeat error (also: no boot-up)
    BUS_OFF = 0x8140
    PDO_TIMEOUT = 0x8250  # here: a TPDO of the cycle did not arrive in time
    FOLLOWING_ERROR = 0x8611
    DEVICE_SOFTWARE = 0x6100  # the drive answered outside the profile
    SDO_TIMEOUT = 0x0504_0000  # SDO abort code "protocol timed out"


def error_register_for(code: int) -> int:
    """Error register (0x1001) bits for an EMCY code: generic bit plus the class bit."""
    reg = 0x01
    top = code >> 12
    if top == 0x2:
        reg |= 0x02  # current
    elif top == 0x3:
        reg |= 0x04  # voltage
    elif top == 0x4:
        reg |= 0x08  # temperature
    elif code >> 8 == 0x81:
        reg |= 0x10  # communication
    elif code >> 8 == 0x86:
        reg |= 0x20  # device profile
    return reg


@dataclass(frozen=True)
class PdoEntry:
    """One object mapped into a PDO."""

    index: int
    subindex: int
    bits: int
    signed: bool
    name: str

    @property
    def mapping(self) -> int:
        """The 32-bit mapping entry (index << 16 | subindex << 8 | bits)."""
        return self.index << 16 | self.subindex << 8 | self.bits

    @property
    def fmt(self) -> str:
        code = {8: "b", 16: "h", 32: "i"}[self.bits]
        return code if self.signed else code.upper()


def pdo_struct(entries: tuple[PdoEntry, ...]) -> struct.Struct:
    """Little-endian packer of a PDO's data bytes."""
    return struct.Struct("<" + "".join(e.fmt for e in entries))


def pdo_bytes(entries: tuple[PdoEntry, ...]) -> int:
    return sum(e.bits for e in entries) // 8


E_TARGET = PdoEntry(TARGET_POSITION, 0, 32, True, "target")
E_CONTROLWORD = PdoEntry(CONTROLWORD, 0, 16, False, "controlword")
E_POSITION = PdoEntry(POSITION_ACTUAL, 0, 32, True, "position")
E_TORQUE_DEMAND = PdoEntry(TORQUE_DEMAND, 0, 16, True, "torque_demand")
E_STATUSWORD = PdoEntry(STATUSWORD, 0, 16, False, "statusword")
E_CURRENT = PdoEntry(CURRENT_ACTUAL, 0, 16, True, "current")
E_TORQUE = PdoEntry(TORQUE_ACTUAL, 0, 16, True, "torque")
E_SYNC_ECHO = PdoEntry(SYNC_ECHO, 0, 8, False, "sync_counter")
E_ERROR_REGISTER = PdoEntry(ERROR_REGISTER, 0, 8, False, "error_register")
E_MODE = PdoEntry(MODES_DISPLAY, 0, 8, True, "mode")


@dataclass(frozen=True)
class PdoLayout:
    """The cyclic exchange of one drive: one synchronous RPDO, two synchronous TPDOs."""

    rpdo: tuple[PdoEntry, ...]
    tpdo1: tuple[PdoEntry, ...]
    tpdo2: tuple[PdoEntry, ...]

    @property
    def tagged(self) -> bool:
        """Every TPDO carries the SYNC counter echo."""
        return all(E_SYNC_ECHO in t for t in (self.tpdo1, self.tpdo2))

    @property
    def tpdos(self) -> tuple[tuple[PdoEntry, ...], ...]:
        return (self.tpdo1, self.tpdo2)

    def frame_bytes(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """Data lengths (rpdo_bytes, tpdo_bytes) for :func:`drivegain.drivers.bus.bus_load`."""
        return (pdo_bytes(self.rpdo),), tuple(pdo_bytes(t) for t in self.tpdos)


#: Layout for drives with the SYNC echo object (the simulated drives): 6 + 8 + 8 bytes.
TAGGED_LAYOUT = PdoLayout(
    rpdo=(E_TARGET, E_CONTROLWORD),
    tpdo1=(E_POSITION, E_TORQUE_DEMAND, E_SYNC_ECHO, E_ERROR_REGISTER),
    tpdo2=(E_STATUSWORD, E_CURRENT, E_TORQUE, E_SYNC_ECHO, E_MODE),
)
#: Layout for drives without it (only standard objects): 6 + 8 + 6 bytes.
PLAIN_LAYOUT = PdoLayout(
    rpdo=(E_TARGET, E_CONTROLWORD),
    tpdo1=(E_POSITION, E_TORQUE_DEMAND, E_STATUSWORD),
    tpdo2=(E_CURRENT, E_TORQUE, E_ERROR_REGISTER, E_MODE),
)


def interpolation_period(period_s: float) -> tuple[int, int]:
    """0x60C2 (value, index) with period = value · 10^index s, value 1..255, index -6..0.

    Raises
    ------
    ConfigError
        The period (a setting of the acquisition) is not representable to 1 µs.
    """
    # Milliseconds first (what drives display), then finer, then coarser units.
    for exponent in (-3, -4, -5, -6, -2, -1, 0):
        value = period_s / 10.0**exponent
        if abs(value - round(value)) < 1e-6 * max(1.0, value) and 1 <= round(value) <= 255:
            return round(value), exponent
    raise ConfigError(
        f"a SYNC period of {period_s} s cannot be written to the drives as 1..255 · 10^-6..0 s "
        f"(interpolation period 0x60C2)"
    )


def period_from_interpolation(value: int, index: int) -> float:
    """Seconds of a 0x60C2 (value, index) pair."""
    return value * 10.0**index


def counts_per_radian(counts_per_rev: int) -> float:
    return counts_per_rev / (2.0 * math.pi)


# --- PDOs of a simulated drive -----------------------------------------------------------------
@dataclass(frozen=True)
class MappedEntry:
    """One entry of a PDO mapping: the object, its struct format and value range."""

    index: int
    subindex: int
    fmt: str
    lo: int
    hi: int

    @classmethod
    def of(cls, index: int, subindex: int, fmt: str) -> MappedEntry:
        bits = struct.calcsize("<" + fmt) * 8
        if fmt.islower():
            return cls(index, subindex, fmt, -(1 << (bits - 1)), (1 << (bits - 1)) - 1)
        return cls(index, subindex, fmt, 0, (1 << bits) - 1)

    @property
    def bits(self) -> int:
        return struct.calcsize("<" + self.fmt) * 8

    def fit(self, value: int) -> int:
        """``value`` in the range of the mapped type: positions (int32) wrap like an encoder
        counter, everything else saturates."""
        if self.lo <= value <= self.hi:
            return value
        if self.fmt == "i":
            return (value - self.lo) % (self.hi - self.lo + 1) + self.lo
        return max(self.lo, min(self.hi, value))


@dataclass
class ActivePdo:
    """A PDO in use by a simulated drive: its mapping, packer and SYNC count."""

    number: int  # 1-based
    cob_id: int
    trans_type: int
    entries: tuple[MappedEntry, ...]
    packer: struct.Struct
    sync_count: int = 0
    #: (index, subindex) of every mapped entry, in order.
    keys: tuple[tuple[int, int], ...] = field(init=False)

    def __post_init__(self) -> None:
        self.keys = tuple((e.index, e.subindex) for e in self.entries)
