"""The ROS 2 ``sensor_msgs/msg/JointState`` twin of ``/joint_states`` (CDR, little endian).

ROS 2 tools (``ros2 bag``) and Foxglove's joint-state panels recognise this schema without any
conversion, so the log carries it beside the contract's JSON channel (contracts §4 allows it;
readers ignore channels they do not know). The message is encoded here, field by field, rather
than through a generic ROS 2 serialiser: its layout is fixed and this is a hot path of the
recorder (one message per SYNC cycle). The tests decode it with ``mcap_ros2``'s decoder.

Content of each message:

- ``header.stamp``: the log time (SYNC time) split into seconds and nanoseconds,
- ``header.frame_id``: empty (joint states have no frame),
- ``name``: the joint names of the log,
- ``position``: joint positions, rad (as ``/joint_states``),
- ``velocity``: empty (the log holds no measured velocity),
- ``effort``: current reference × drive gain, N·m, when the writer was given gains; empty
  otherwise (a log alone does not know its drive gains: identifying them is the point).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

import numpy as np

SCHEMA_NAME = "sensor_msgs/msg/JointState"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"

_RULE = "=" * 80
#: The message definition with its dependencies, in the concatenated form ROS 2 bags use.
SCHEMA_TEXT = "\n".join(
    [
        "std_msgs/Header header",
        "string[] name",
        "float64[] position",
        "float64[] velocity",
        "float64[] effort",
        _RULE,
        "MSG: std_msgs/Header",
        "builtin_interfaces/Time stamp",
        "string frame_id",
        _RULE,
        "MSG: builtin_interfaces/Time",
        "int32 sec",
        "uint32 nanosec",
        "",
    ]
)

#: CDR encapsulation header: plain CDR, little endian, no options.
_ENCAPSULATION = b"\x00\x01\x00\x00"


def _pad(offset: int, align: int) -> int:
    """Bytes of padding that bring ``offset`` (from the start of the CDR body) to ``align``."""
    return -offset % align


def _string(out: bytearray, text: str) -> None:
    data = text.encode("utf-8") + b"\x00"
    out += b"\x00" * _pad(len(out), 4)
    out += struct.pack("<I", len(data)) + data


class JointStateEncoder:
    """Encodes one ``sensor_msgs/msg/JointState`` per cycle for fixed joint names.

    Parameters
    ----------
    joint_names
        The names, in the order of the position vectors.
    effort_gains
        Drive gains, N·m/A per joint: efforts are current reference × gain. ``None`` leaves
        ``effort`` empty.
    """

    def __init__(self, joint_names: Sequence[str], effort_gains: Sequence[float] | None = None):
        self.n = len(joint_names)
        self.gains = None if effort_gains is None else np.asarray(effort_gains, dtype=float)
        if self.gains is not None and self.gains.shape != (self.n,):
            raise ValueError(f"{self.gains.size} effort gains for {self.n} joints")
        # Everything after the stamp up to the position values is the same in every message.
        body = bytearray(8)  # stamp: int32 sec, uint32 nanosec (filled per message)
        _string(body, "")  # frame_id
        body += b"\x00" * _pad(len(body), 4)
        body += struct.pack("<I", self.n)
        for name in joint_names:
            _string(body, name)
        self._middle = bytes(body[8:])
        self._offset = len(body)  # body offset where the position sequence starts

    def _array(self, out: bytearray, values: np.ndarray | None) -> None:
        out += b"\x00" * _pad(len(out) - 4, 4)
        if values is None or values.size == 0:
            out += struct.pack("<I", 0)
            return
        out += struct.pack("<I", values.size)
        out += b"\x00" * _pad(len(out) - 4, 8)
        out += np.ascontiguousarray(values, dtype="<f8").tobytes()

    def encode(
        self, log_time_ns: int, position: np.ndarray, current_reference: np.ndarray | None
    ) -> bytes:
        """The CDR bytes of one message (encapsulation header included).

        Parameters
        ----------
        log_time_ns
            Time stamp, ns since the Unix epoch (or since the simulation's start in lockstep).
        position
            Joint positions, rad, (n,).
        current_reference
            Current references, A, (n,); used for the efforts when gains are known.
        """
        sec, nanosec = divmod(int(log_time_ns), 1_000_000_000)
        out = bytearray(_ENCAPSULATION)
        out += struct.pack("<iI", sec, nanosec)
        out += self._middle
        pos = np.asarray(position, dtype=float)
        self._array(out, pos)
        self._array(out, None)  # velocity: not measured
        effort = None
        if self.gains is not None and current_reference is not None:
            effort = np.asarray(current_reference, dtype=float) * self.gains
        self._array(out, effort)
        return bytes(out)
