"""Faults the simulated drives can be told to produce, per node and simulated time."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

from drivegain.config._toml import Table
from drivegain.config.schema import SettingError, load_table, setting
from drivegain.drivers.objects import EmcyCode


class FaultKind(StrEnum):
    """What goes wrong.

    - ``emcy``: the drive sends an EMCY (default code 0x8611 following error) and enters FAULT;
    - ``fault``: the drive enters FAULT silently (0x603F holds the code, default 0x2310);
    - ``heartbeat_stop``: the node stops producing heartbeats (PDOs continue);
    - ``tpdo_missing``: the node stops sending its TPDOs (``tpdo`` = 1 or 2, default both);
    - ``tpdo_late``: its TPDOs leave ``delay_s`` after the SYNC;
    - ``never_boots``: the node never sends a boot-up and answers nothing;
    - ``bus_error``: a bus-off error frame appears on the bus (bus-wide, no node).
    """

    EMCY = "emcy"
    FAULT = "fault"
    HEARTBEAT_STOP = "heartbeat_stop"
    TPDO_MISSING = "tpdo_missing"
    TPDO_LATE = "tpdo_late"
    NEVER_BOOTS = "never_boots"
    BUS_ERROR = "bus_error"


class FaultValueError(SettingError):
    """An impossible fault specification; ``key`` names the field at fault."""


DEFAULT_CODES = {
    FaultKind.EMCY: int(EmcyCode.FOLLOWING_ERROR),
    FaultKind.FAULT: int(EmcyCode.CONTINUOUS_OVERCURRENT),
}


@dataclass(frozen=True)
class FaultSpec:
    """One injected fault.

    Attributes
    ----------
    kind
        What happens (:class:`FaultKind`).
    node
        CANopen node id of the drive; ``None`` for ``bus_error``.
    at_s
        Simulated seconds after the first SYNC (ignored by ``never_boots``).
    code
        Error code for ``emcy`` / ``fault`` (defaults 0x8611 / 0x2310).
    delay_s
        Delay of the TPDOs for ``tpdo_late``, s.
    tpdo
        TPDO number (1 or 2) for ``tpdo_missing`` / ``tpdo_late``; ``None`` = every TPDO.
    """

    kind: FaultKind = field(metadata=setting(doc="what happens"))
    node: int | None = field(
        default=None, metadata=setting(doc="CANopen node id of the drive (none for bus_error)")
    )
    at_s: float = field(
        default=0.0, metadata=setting(unit="s", doc="simulated time after the first SYNC")
    )
    code: int | None = field(
        default=None, metadata=setting(doc="error code of emcy / fault (default per kind)")
    )
    delay_s: float = field(
        default=0.0, metadata=setting(unit="s", doc="delay of the TPDOs of tpdo_late")
    )
    tpdo: int | None = field(
        default=None, metadata=setting(doc="TPDO number 1 or 2 (default every TPDO)")
    )

    def __post_init__(self) -> None:
        if self.kind == FaultKind.BUS_ERROR:
            if self.node is not None:
                raise FaultValueError("node", "a bus error has no node")
        elif self.node is None or not 1 <= self.node <= 127:
            raise FaultValueError("node", f"{self.kind}: needs a node id 1..127, got {self.node}")
        if self.at_s < 0.0:
            raise FaultValueError("at_s", f"must be >= 0, got {self.at_s}")
        if self.kind == FaultKind.TPDO_LATE and self.delay_s <= 0.0:
            raise FaultValueError("delay_s", "tpdo_late needs delay_s > 0")
        if self.tpdo is not None and self.tpdo not in (1, 2):
            raise FaultValueError("tpdo", f"must be 1 or 2, got {self.tpdo}")
        if self.code is not None and not 0 < self.code <= 0xFFFF:
            raise FaultValueError("code", f"must be a 16-bit EMCY code, got {self.code}")

    @property
    def effective_code(self) -> int | None:
        """The error code the drive reports for this fault, if any."""
        if self.code is not None:
            return self.code
        return DEFAULT_CODES.get(self.kind)


def fault_from_table(t: Table) -> FaultSpec:
    """One ``[[simulation.fault]]`` table (keys kind, node, at_s, code, delay_s, tpdo).

    Raises
    ------
    ConfigError
        One line naming the file and the key at fault.
    """
    return load_table(FaultSpec, t)
