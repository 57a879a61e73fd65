"""What every part of the master shares about one drive: its record, the time limits, and the two
ways to talk to it (a raw frame on the bus, a typed SDO transfer through canopen).

The master is split by job (:mod:`.configure`, :mod:`.exchange`, :mod:`.supervisor`,
:mod:`.statewalk`, with :mod:`.master` as the facade); they all hold the same :class:`DriveLink`
records and map canopen and python-can failures to the drivegain error tree here, so that every
error names the node and carries the SDO abort code or the EMCY code.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass

import can
import canopen
from canopen.objectdictionary import ObjectDictionary, ObjectDictionaryError, ODVariable
from canopen.sdo import SdoAbortedError, SdoCommunicationError, SdoVariable

from drivegain.drivers import objects as ob
from drivegain.drivers.bus import TPDO_TIMEOUT_LOCKSTEP_S
from drivegain.drivers.cia402 import State
from drivegain.errors import BusError, ConfigError, DriveError


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
    tpdo_s: float = TPDO_TIMEOUT_LOCKSTEP_S
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


@dataclass
class DriveLink:
    """One drive as the master sees it.

    Attributes
    ----------
    joint
        Index of the joint in the robot file.
    node_id
        CANopen node id.
    node
        canopen's remote node (object dictionary from the EDS, SDO client, PDO maps).
    cpr
        Encoder counts per motor radian.
    rated_a
        Motor rated current, A (the drive's 0x6075 once booted): scales the per-mille currents.
    nmt
        Last NMT state seen in a heartbeat (None before the first).
    last_heartbeat
        When the last heartbeat was sent, on the master's clock (:mod:`.simtime`), s (None
        until the consumer starts).
    silence_reported
        When the last heartbeat time-out was reported, on the master's clock, s.
    state
        Last CiA 402 state seen (statusword by SDO or TPDO).
    """

    joint: int
    node_id: int
    node: canopen.RemoteNode
    cpr: float
    rated_a: float
    nmt: int | None = None
    last_heartbeat: float | None = None
    silence_reported: float = 0.0
    state: State | None = None


#: Objects the master reads or writes by SDO on every drive (index, subindex): the EDS must
#: describe them, since typed SDO access takes the data type from it.
REQUIRED_OBJECTS = (
    (ob.DEVICE_TYPE, 0),
    (ob.CONSUMER_HEARTBEAT, 1),
    (ob.PRODUCER_HEARTBEAT, 0),
    (ob.RPDO_COMM, 1),
    (ob.RPDO_MAP, 0),
    (ob.TPDO_COMM, 1),
    (ob.TPDO_MAP, 0),
    (ob.TPDO_COMM + 1, 1),
    (ob.TPDO_MAP + 1, 0),
    (ob.ERROR_CODE, 0),
    (ob.CONTROLWORD, 0),
    (ob.STATUSWORD, 0),
    (ob.MODES_OF_OPERATION, 0),
    (ob.MODES_DISPLAY, 0),
    (ob.POSITION_ACTUAL, 0),
    (ob.RATED_CURRENT, 0),
    (ob.TARGET_POSITION, 0),
    (ob.INTERPOLATION_PERIOD, 1),
    (ob.INTERPOLATION_PERIOD, 2),
)


def missing_objects(od: ObjectDictionary, wanted: tuple[tuple[int, int], ...]) -> list[str]:
    """The entries of ``wanted`` (index, subindex) that ``od`` lacks, as ``"0xIIII:SS"``."""
    missing = []
    for index, subindex in wanted:
        obj = od.get(index)
        if isinstance(obj, ODVariable):
            continue
        try:
            if obj is not None:
                obj[subindex]
                continue
        except KeyError:
            pass
        missing.append(f"0x{index:04X}:{subindex:02X}")
    return missing


def send(network: canopen.Network, cob: int, data: bytes) -> None:
    """Put one frame on the bus.

    Raises
    ------
    BusError
        The interface refused the frame, or the bus reader thread failed.
    """
    try:
        network.send_message(cob, data)
    except (can.CanError, OSError) as exc:
        raise BusError(f"cannot send frame 0x{cob:03X}: {exc}") from None
    except Exception as exc:  # network.check() re-raises the reader thread's failure
        raise BusError(f"CAN bus failed: {exc}") from None


@contextlib.contextmanager
def sdo_errors(d: DriveLink, what: str) -> Iterator[None]:
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
    except ObjectDictionaryError as exc:  # an answer shorter than the object's data type
        raise DriveError(f"SDO {what}: {exc}", node=d.node_id) from None
    except (can.CanError, OSError) as exc:
        raise BusError(f"SDO {what} on node {d.node_id} failed: {exc}") from None


def sdo_variable(d: DriveLink, index: int, subindex: int = 0) -> SdoVariable:
    """canopen's typed SDO access to one object of the drive (data type from the EDS)."""
    obj = d.node.sdo[index]
    return obj if isinstance(obj, SdoVariable) else obj[subindex]


def sdo_read(d: DriveLink, index: int, subindex: int = 0) -> int:
    """Read an integer object by SDO (``node.sdo[index][subindex].raw``).

    Raises
    ------
    DriveError
        Abort (code = abort code), no answer (code 0x05040000), or a short answer.
    BusError
        The interface failed.
    """
    with sdo_errors(d, f"read 0x{index:04X}:{subindex:02X}"):
        return int(sdo_variable(d, index, subindex).raw)


def sdo_write(d: DriveLink, index: int, subindex: int, value: int) -> None:
    """Write an integer object by SDO, encoded with its EDS data type (expedited transfer).

    Raises
    ------
    DriveError, BusError
        As :func:`sdo_read`.
    """
    with sdo_errors(d, f"write 0x{index:04X}:{subindex:02X} = {value}"):
        sdo_variable(d, index, subindex).raw = value


def error_code(d: DriveLink) -> int | None:
    """0x603F of a drive (None if it cannot be read or is 0): context for a fault report."""
    try:
        code = sdo_read(d, ob.ERROR_CODE)
    except DriveError:
        return None
    return code or None
