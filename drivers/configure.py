"""Configuration of each drive between NMT reset and NMT start, through canopen's typed SDO access
and its PDO maps (``node.rpdo`` / ``node.tpdo``).

Per drive: device type (CiA 402), cyclic synchronous position support (0x6502), rated current
(0x6075), encoder resolution (0x608F, checked against the robot file), PDO mapping (RPDO1 target
+ controlword, TPDO1/TPDO2 synchronous, the other predefined PDOs disabled), SYNC counter
overflow (0x1019), heartbeat producer (0x1017), consumer of the master's heartbeat (0x1016 sub 1:
a drive that misses it goes to its fault reaction), interpolation period (0x60C2), mode of
operation 0x6060 = 8 (checked in 0x6061).

Every PDO is reconfigured as CiA 301 requires, which is what canopen's ``PdoMap.save()`` sends
once its optional parameters are left unset: COB-ID with the "not valid" bit, transmission type,
mapping count 0, the entries, the count, COB-ID valid again.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from canopen.objectdictionary import ObjectDictionary, ODRecord
from canopen.pdo import PdoMap

from drivegain.config.robot import Robot
from drivegain.drivers import objects as ob
from drivegain.drivers.link import (
    REQUIRED_OBJECTS,
    DriveLink,
    missing_objects,
    sdo_errors,
    sdo_read,
    sdo_write,
)
from drivegain.drivers.supervisor import Supervisor
from drivegain.errors import ConfigError, DriveError
from drivegain.formats.log import EventLevel

#: Transmission type "synchronous, every SYNC" (0x1400/0x1800 sub 2).
SYNCHRONOUS = 1


class DriveConfigurator:
    """Writes the master's configuration into each drive by SDO.

    Parameters
    ----------
    robot
        The robot file (encoder resolution, rated current, its path for errors).
    od
        Object dictionary of the drives' EDS (every drive of a master shares one EDS).
    eds
        Path of that EDS, for errors.
    layout
        The cyclic PDO layout to map.
    sync_counter
        The SYNC carries a counter: write its overflow value (0x1019).
    heartbeat_ms
        Heartbeat producer period to write (0x1017), ms.
    consumer
        The drive's consumer of the master's heartbeat to write (0x1016 sub 1: master node id
        << 16 | time-out in ms).
    interpolation
        Interpolation period (value, index) to write (0x60C2 sub 1, 2).
    supervisor
        Where warnings go.

    Raises
    ------
    ConfigError
        The EDS lacks an object the master reads or writes, or its PDO mapping is not writable.
    """

    def __init__(
        self,
        robot: Robot,
        od: ObjectDictionary,
        eds: Path,
        layout: ob.PdoLayout,
        *,
        sync_counter: bool,
        heartbeat_ms: int,
        consumer: int,
        interpolation: tuple[int, int],
        supervisor: Supervisor,
    ):
        self.robot = robot
        self.od = od
        self.eds = eds
        self.layout = layout
        self.sync_counter = sync_counter
        self.heartbeat_ms = heartbeat_ms
        self.consumer = consumer
        self.interpolation = interpolation
        self.supervisor = supervisor
        self._check_eds()

    def _check_eds(self) -> None:
        """Typed SDO access and canopen's PDO maps take data types and sub-indexes from the EDS:
        refuse one that lacks what the master writes, rather than fail half-way through a boot."""
        maps = (
            (ob.RPDO_MAP, self.layout.rpdo),
            *zip((ob.TPDO_MAP, ob.TPDO_MAP + 1), self.layout.tpdos, strict=True),
        )
        comms = (ob.RPDO_COMM, ob.TPDO_COMM, ob.TPDO_COMM + 1)
        wanted = [*REQUIRED_OBJECTS, *((comm, 2) for comm in comms)]
        for index, entries in maps:
            wanted += [(index, k) for k in range(len(entries) + 1)]
            wanted += [(e.index, e.subindex) for e in entries]
        missing = missing_objects(self.od, tuple(wanted))
        if missing:
            raise ConfigError(f"the drive EDS lacks object(s) {', '.join(missing)}", file=self.eds)
        for index, entries in maps:
            record = self.od[index]
            if not isinstance(record, ODRecord):
                # canopen 2.4's PdoMap.save() sizes an ARRAY by reading its sub 0 by SDO, after
                # writing it 0: it would write no entry at all.
                raise ConfigError(
                    f"PDO mapping 0x{index:04X} must be a RECORD (ObjectType=0x9) in the drive "
                    f"EDS, as CiA 301 defines it",
                    file=self.eds,
                )
            # canopen's PdoMap.save() silently skips entries the EDS calls read-only: a static
            # mapping would then be enabled as it is, not as the master decodes it.
            fixed = [
                f"0x{index:04X}:{k:02X}" for k in range(len(entries) + 1) if not record[k].writable
            ]
            if fixed:
                raise ConfigError(
                    f"PDO mapping {', '.join(fixed)} is read-only in the drive EDS "
                    f"(the master needs a configurable mapping)",
                    file=self.eds,
                )

    def configure(self, d: DriveLink) -> None:
        """Configure one drive (NMT pre-operational, after boot-up).

        Raises
        ------
        DriveError
            The drive refused a setting, did not answer, or is not a CSP-capable CiA 402 drive.
        ConfigError
            The drive disagrees with the robot file (encoder resolution).
        BusError
            The interface failed.
        """
        self._check_profile(d)
        self._read_rated_current(d)
        self._check_encoder(d)
        self._map_pdos(d)
        if self.sync_counter:
            sdo_write(d, ob.SYNC_OVERFLOW, 0, ob.SYNC_COUNTER_OVERFLOW)
        sdo_write(d, ob.PRODUCER_HEARTBEAT, 0, self.heartbeat_ms)
        sdo_write(d, ob.CONSUMER_HEARTBEAT, 1, self.consumer)
        value, index = self.interpolation
        sdo_write(d, ob.INTERPOLATION_PERIOD, 1, value)
        sdo_write(d, ob.INTERPOLATION_PERIOD, 2, index)
        sdo_write(d, ob.MODES_OF_OPERATION, 0, ob.MODE_CSP)
        mode = sdo_read(d, ob.MODES_DISPLAY)
        if mode != ob.MODE_CSP:
            raise DriveError(
                f"mode of operation display is {mode}, expected {ob.MODE_CSP} (CSP)",
                node=d.node_id,
            )

    def _check_profile(self, d: DriveLink) -> None:
        device_type = sdo_read(d, ob.DEVICE_TYPE)
        if device_type & 0xFFFF != ob.PROFILE_402:
            raise DriveError(
                f"not a CiA 402 drive (device type 0x{device_type:08X})", node=d.node_id
            )
        if ob.SUPPORTED_MODES in self.od:
            modes = sdo_read(d, ob.SUPPORTED_MODES)
            if not modes & ob.SUPPORTED_CSP_BIT:
                raise DriveError(
                    f"no cyclic synchronous position mode (0x6502 = 0x{modes:08X})",
                    node=d.node_id,
                )

    def _read_rated_current(self, d: DriveLink) -> None:
        """The drive's 0x6075 scales its per-mille currents: it wins over the robot file."""
        joint = self.robot.joints[d.joint]
        rated_ma = sdo_read(d, ob.RATED_CURRENT)
        if rated_ma == 0:
            raise DriveError("motor rated current 0x6075 is 0", node=d.node_id)
        d.rated_a = rated_ma / 1000.0
        if abs(d.rated_a - joint.rated_current) > 0.01 * joint.rated_current:
            self.supervisor.event(
                EventLevel.WARNING,
                d.node_id,
                None,
                f"drive rated current {d.rated_a} A differs from the robot file "
                f"({joint.rated_current} A); the drive's value scales the currents",
            )

    def _check_encoder(self, d: DriveLink) -> None:
        if ob.ENCODER_RESOLUTION not in self.od:
            return
        joint = self.robot.joints[d.joint]
        increments = sdo_read(d, ob.ENCODER_RESOLUTION, 1)
        revolutions = sdo_read(d, ob.ENCODER_RESOLUTION, 2)
        if revolutions == 0 or increments != joint.encoder_counts * revolutions:
            raise ConfigError(
                f"drive {d.node_id} reports {increments} counts per {revolutions} "
                f"revolution(s), the robot file says {joint.encoder_counts}",
                file=self.robot.source,
                key=f"joint[{d.joint}].encoder_counts",
            )

    def _map_pdos(self, d: DriveLink) -> None:
        """RPDO2..4 and TPDO3..4 off, then RPDO1, TPDO1, TPDO2 mapped and synchronous."""
        rpdo, tpdo = d.node.rpdo.map, d.node.tpdo.map
        assert rpdo is not None and tpdo is not None  # a RemoteNode always has both
        for unused in (*(rpdo.get(k) for k in (2, 3, 4)), *(tpdo.get(k) for k in (3, 4))):
            if unused is not None:
                self._disable(d, unused)
        self._map(d, rpdo[1], self.layout.rpdo)
        self._map(d, tpdo[1], self.layout.tpdo1)
        self._map(d, tpdo[2], self.layout.tpdo2)

    def _disable(self, d: DriveLink, pdo: PdoMap) -> None:
        """Set the "not valid" bit of a predefined PDO's COB-ID (one SDO write, nothing else:
        ``save()`` would also rewrite its mapping)."""
        assert pdo.predefined_cob_id is not None  # maps 1..4 are all predefined
        pdo.cob_id = pdo.predefined_cob_id
        pdo.enabled = False
        sdo_write(d, pdo.com_record.od.index, 1, ob.PDO_INVALID | pdo.cob_id)

    def _map(self, d: DriveLink, pdo: PdoMap, entries: Sequence[ob.PdoEntry]) -> None:
        """Map ``entries`` into ``pdo`` on its predefined COB-ID, synchronous (CiA 301 §7.5.2.36
        order: disable, transmission type, count 0, entries, count, enable)."""
        assert pdo.predefined_cob_id is not None
        pdo.clear()
        for e in entries:
            # Present in the EDS (checked at construction): add_variable only returns None,
            # after logging, for an object it cannot find.
            added = pdo.add_variable(e.index, e.subindex, e.bits)
            assert added is not None
        pdo.cob_id = pdo.predefined_cob_id
        pdo.enabled = True
        pdo.rtr_allowed = True  # the COB-ID goes out without bit 30, as before
        pdo.trans_type = SYNCHRONOUS
        # Left unset, save() does not write them: the drives' defaults apply (synchronous PDOs
        # ignore inhibit time and event timer; no SYNC start value).
        pdo.inhibit_time = pdo.event_timer = pdo.sync_start_value = None
        comm, mapping = pdo.com_record.od.index, pdo.map_array.od.index
        with sdo_errors(d, f"configure PDO 0x{comm:04X}/0x{mapping:04X}"):
            pdo.save()
        # save() subscribed canopen's per-PDO callback; the master's own listener sees every
        # frame already, and canopen's would only add work to each TPDO in the reader thread.
        network = d.node.network
        if pdo.on_message in network.subscribers.get(pdo.cob_id, ()):
            network.unsubscribe(pdo.cob_id, pdo.on_message)
