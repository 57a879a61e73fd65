"""The acquisition log: MCAP files per contracts.md §4 (``format_version`` 1).

What writer and reader share lives here: channel names, the ``drivegain.run`` metadata record,
the event levels, the JSON schemas of ``/joint_states``, ``/drives/raw`` and ``/events``; the
ROS 2 ``sensor_msgs/msg/JointState`` channel is :mod:`.ros2`. Writing is :mod:`.logwriter`, reading
:mod:`.logreader`.

Every problem with a file is a :class:`~drivegain.errors.DataError` whose one-line message names
the file and, where it applies, the message, cycle, field and joint.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import StrEnum
from typing import TYPE_CHECKING, Any

from drivegain import __version__
from drivegain.errors import DataError, UsageError

if TYPE_CHECKING:
    from drivegain.config.payload import Payload
    from drivegain.config.robot import Robot

FORMAT_VERSION = "1"
JOINT_STATES = "/joint_states"
RAW = "/drives/raw"
EVENTS = "/events"
#: the ROS 2 ``sensor_msgs/msg/JointState`` (CDR) twin of ``/joint_states``; its own topic, since
#: ``/joint_states`` is the contract's JSON channel
ROS2_JOINT_STATES = "/ros2/joint_states"
#: the rows of ``/joint_states`` again, in blocks of arrays, for fast reading (:mod:`.columns`)
JOINT_STATE_COLUMNS = "/joint_states/columns"
METADATA_NAME = "drivegain.run"
#: keys every ``drivegain.run`` metadata record must hold
REQUIRED_KEYS = (
    "format_version",
    "robot",
    "run",
    "payload",
    "joint_names",
    "sync_period_s",
    "started_at",
    "drivegain_version",
)
#: the per-joint vector fields of a ``/joint_states`` message
VECTOR_FIELDS = ("position", "current_reference", "current", "setpoint")
#: vector fields identification cannot do without; ``current`` and ``setpoint`` may be null
REQUIRED_VECTORS = ("position", "current_reference")
DEFAULT_CHUNK_SIZE = 1 << 20


class EventLevel(StrEnum):
    """Severity of an event on ``/events`` (contracts §4): the value is what the log holds."""

    INFO = "info"
    WARNING = "warning"
    ERROR = "error"


@dataclass(frozen=True)
class RunMetadata:
    """What the ``drivegain.run`` metadata record says about a run.

    Parameters
    ----------
    robot
        Robot name (the robot file's ``robot.name``).
    run
        ``unloaded``, ``loaded`` or a free label.
    payload
        Payload name, or ``none``.
    joint_names
        Names of the joints, in the order of every vector in the log.
    sync_period_s
        SYNC period, s.
    started_at
        ISO 8601 UTC time of the first cycle.
    drivegain_version
        Version of the program that wrote the log.
    extra
        More string keys stored in the same record (must not reuse the keys above).
    """

    robot: str
    run: str
    payload: str
    joint_names: list[str]
    sync_period_s: float
    started_at: str
    drivegain_version: str = __version__
    extra: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.joint_names or len(set(self.joint_names)) != len(self.joint_names):
            raise DataError(
                f"must be unique and non-empty, got {self.joint_names}", key="joint_names"
            )
        if not (math.isfinite(self.sync_period_s) and self.sync_period_s > 0):
            raise DataError(f"must be positive, got {self.sync_period_s}", key="sync_period_s")
        clash = set(self.extra) & set(REQUIRED_KEYS)
        if clash:
            raise UsageError(f"extra metadata reuses reserved keys {sorted(clash)}")
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in self.extra.items()):
            raise UsageError("extra metadata keys and values must be strings")

    def to_record(self) -> dict[str, str]:
        """The string map stored in the MCAP metadata record.

        MCAP metadata records are maps of strings to strings (MCAP specification, "Metadata"),
        so numbers are stored as their shortest exact text (``repr`` of the float) and lists as
        JSON; readers parse them back. Numbers inside messages (``/events`` fields) are JSON
        numbers.
        """
        record = {
            "format_version": FORMAT_VERSION,
            "robot": self.robot,
            "run": self.run,
            "payload": self.payload,
            "joint_names": json.dumps(list(self.joint_names)),
            "sync_period_s": repr(float(self.sync_period_s)),
            "started_at": self.started_at,
            "drivegain_version": self.drivegain_version,
        }
        record.update(self.extra)
        return record


def run_metadata(
    robot: Robot,
    run: str,
    payload: Payload | None,
    sync_period_s: float,
    started_at: str,
    extra: dict[str, str] | None = None,
) -> RunMetadata:
    """The ``drivegain.run`` record of a run of ``robot`` carrying ``payload``.

    Parameters
    ----------
    robot
        The robot: its name and joint names go into the record.
    run
        ``unloaded``, ``loaded`` or a free label.
    payload
        The payload carried, or ``None`` (recorded as ``none``).
    sync_period_s
        SYNC (sample) period, s.
    started_at
        ISO 8601 UTC time of the first cycle (:func:`utc_iso`, :func:`utc_now_iso`).
    extra
        More string keys (see :class:`RunMetadata`).

    Raises
    ------
    DataError
        Duplicate joint names or a period that is not positive.
    UsageError
        ``extra`` reuses a reserved key or holds a value that is not a string.
    """
    return RunMetadata(
        robot=robot.name,
        run=run,
        payload=payload.name if payload is not None else "none",
        joint_names=robot.joint_names,
        sync_period_s=sync_period_s,
        started_at=started_at,
        extra={} if extra is None else extra,
    )


def utc_iso(epoch_s: float) -> str:
    """``epoch_s`` (s since the Unix epoch) as ISO 8601 UTC with milliseconds, ``...Z``."""
    return _iso_z(datetime.fromtimestamp(epoch_s, UTC))


def utc_now_iso() -> str:
    """The current time as ISO 8601 UTC (second resolution is enough for a run's start)."""
    return _iso_z(datetime.now(UTC))


def _iso_z(when: datetime) -> str:
    return when.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _vector_schema(description: str) -> dict[str, Any]:
    return {
        "type": "array",
        "items": {"type": ["number", "null"]},
        "description": description + " (null: not available or not finite)",
    }


def joint_state_schema(joint_names: Sequence[str]) -> dict[str, Any]:
    """JSON schema (draft 2020-12) of a ``/joint_states`` message for these joints."""
    n = len(joint_names)
    props: dict[str, Any] = {
        "cycle": {"type": "integer", "description": "SYNC cycle index since the run start"},
        "t": {"type": "number", "description": "seconds since the first cycle"},
        "position": _vector_schema("joint positions, rad, joint side, controller convention"),
        "current_reference": _vector_schema("current reference of each drive, A"),
        "current": _vector_schema("measured current of each drive, A"),
        "setpoint": _vector_schema("commanded joint positions, rad"),
        "name": {
            "type": "array",
            "items": {"type": "string"},
            "description": "joint names, the order of every vector (optional, contracts §4)",
        },
    }
    for name in (*VECTOR_FIELDS, "name"):
        props[name]["minItems"] = n
        props[name]["maxItems"] = n
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "drivegain.JointState",
        "description": "one SYNC cycle; vectors ordered as " + ", ".join(joint_names),
        "type": "object",
        "properties": props,
        "required": ["cycle", "t", *VECTOR_FIELDS],
    }


#: The per-joint integer arrays of a ``/drives/raw`` message, as the drives sent them (the
#: acquisition's ``drivers.exchange.RAW_FIELDS``; a test keeps the two lists equal).
RAW_FIELD_DOCS: dict[str, str] = {
    "position": "position actual value 0x6064, encoder counts (motor side)",
    "torque_demand": "torque demand 0x6074, per mille of the rated torque (the current reference)",
    "current": "current actual value 0x6078, per mille of the rated current 0x6075",
    "torque": "torque actual value 0x6077, per mille of the rated torque",
    "statusword": "CiA 402 statusword 0x6041",
    "error_register": "error register 0x1001",
    "mode": "modes of operation display 0x6061",
    "sync_counter": "SYNC counter echoed in the TPDOs (or that of the SYNC sent, if not echoed)",
    "target": "target position sent in the RPDO, encoder counts (motor side)",
}


def raw_schema(joint_names: Sequence[str]) -> dict[str, Any]:
    """JSON schema (draft 2020-12) of a ``/drives/raw`` message for these joints.

    Each raw field is an array of integers with one value per joint, in ``joint_names`` order
    (the drive of joint j; its node id is in the robot TOML attachment).
    """
    n = len(joint_names)
    order = ", ".join(joint_names)
    fields = {
        name: {
            "type": "array",
            "items": {"type": "integer"},
            "minItems": n,
            "maxItems": n,
            "description": f"{doc}; one per joint, ordered as {order}",
        }
        for name, doc in RAW_FIELD_DOCS.items()
    }
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "drivegain.DrivesRaw",
        "description": (
            "one SYNC cycle as the drives sent it, before any conversion (counts, per-mille "
            "values, statuswords), so every conversion can be redone; log time = SYNC time, ns"
        ),
        "type": "object",
        "properties": {
            "cycle": {
                "type": "integer",
                "minimum": 0,
                "description": "SYNC cycle index since the run start (as in /joint_states)",
            },
            "raw": {
                "type": "object",
                "description": "raw field name -> one integer per joint",
                "properties": fields,
                # a drive profile may map more objects: still one integer per joint
                "additionalProperties": {
                    "type": "array",
                    "items": {"type": "integer"},
                    "minItems": n,
                    "maxItems": n,
                },
            },
        },
        "required": ["cycle", "raw"],
    }


EVENT_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "drivegain.Event",
    "description": (
        "EMCY, NMT or CiA 402 state change, fault, warning, operator stop, phase change. Log "
        "time = when the master recorded it, ns; events of one log time are in the order of "
        "their MCAP sequence numbers. Numeric extra fields are JSON numbers."
    ),
    "type": "object",
    "properties": {
        "level": {"type": "string", "enum": [lv.value for lv in EventLevel]},
        "node": {
            "type": ["integer", "null"],
            "description": "CANopen node id of the drive concerned, null for the whole cell",
        },
        "code": {
            "type": ["integer", "null"],
            "description": "EMCY or CiA 402 error code (0x1003 / 0x603F), null if none",
        },
        "text": {"type": "string", "description": "what happened, one line"},
        "drive_time_ns": {
            "type": "integer",
            "description": (
                "wall-clock time (Unix epoch, ns) at which the master noticed the drive's "
                "message (EMCY frame, state change, heartbeat loss). The log time is the SYNC "
                "time base: the wall clock in realtime (so the two differ by the queueing "
                "between the CAN thread and the cycle loop), simulated time in lockstep (so "
                "only this field says when it happened in the real world)"
            ),
        },
        "phase": {"type": "string", "description": "approach, excitation or retreat"},
        "cycle": {"type": "integer", "description": "SYNC cycle index the event refers to"},
    },
    "required": ["level", "node", "code", "text"],
    "additionalProperties": True,
}
