"""The acquisition log: MCAP files per contracts.md §4 (``format_version`` 1).

What writer and reader share lives here: channel names, the ``drivegain.run`` metadata record,
the event levels and the ``/joint_states`` JSON schema. Writing is :mod:`.logwriter`, reading
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
from typing import Any

from drivegain import __version__
from drivegain.errors import DataError, UsageError

FORMAT_VERSION = "1"
JOINT_STATES = "/joint_states"
RAW = "/drives/raw"
EVENTS = "/events"
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
        """The string map stored in the MCAP metadata record."""
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


def utc_now_iso() -> str:
    """The current time as ISO 8601 UTC (second resolution is enough for a run's start)."""
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


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
    }
    for name in VECTOR_FIELDS:
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


RAW_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "drivegain.DrivesRaw",
    "description": "raw values as the drives sent them in one SYNC cycle, keyed by node",
    "type": "object",
    "properties": {"cycle": {"type": "integer"}, "raw": {"type": "object"}},
    "required": ["cycle", "raw"],
}

EVENT_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "drivegain.Event",
    "description": "EMCY, NMT or CiA 402 state change, fault, warning, operator stop, phase",
    "type": "object",
    "properties": {
        "level": {"type": "string"},
        "node": {"type": ["integer", "null"]},
        "code": {"type": ["integer", "null"]},
        "text": {"type": "string"},
    },
    "required": ["level", "node", "code", "text"],
}
