"""The ``/joint_states/columns`` side channel: blocks of ``/joint_states`` rows as arrays.

A 10-minute run at 1 kHz holds 600 000 ``/joint_states`` JSON messages, and decoding them is most
of the time ``identify`` spends reading such a log. The writer therefore stores the same rows a
second time, in blocks of up to :data:`BLOCK_ROWS`, as whole little-endian arrays: one MessagePack
map per block (message encoding ``msgpack``, self-describing, no schema), written after the JSON
messages of its rows. ``/joint_states`` stays the contract's channel (contracts.md §4): tools that
do not know this channel ignore it, and the reader uses it only when it agrees with the JSON
messages (:mod:`.logreader`).

A block's map has the keys ``version`` (1), ``rows`` (k), ``joints`` (n), and one byte string per
field: ``cycle`` and ``log_time_ns`` (k int64), ``t`` (k float64), and ``position``,
``current_reference``, ``current``, ``setpoint`` (k × n float64, row-major). A value that is null
in the JSON message (not measured, or not finite) is NaN here, as the JSON reader stores it.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from typing import Any

import msgspec
import numpy as np

from drivegain.formats.log import VECTOR_FIELDS

__all__ = ["BLOCK_ROWS", "SPOT_EVERY", "VERSION", "ColumnBuffer", "ColumnCheck", "decode_block"]

#: Rows per block: a block of six joints is then 55 kB, so a chunk (1 MiB) is not stretched much
#: by the message that closes it; large enough that a block's fixed costs vanish.
BLOCK_ROWS = 256
#: The layout of a block's map; a reader that does not know a block's version (or finds keys it
#: does not know) reads the JSON messages instead.
VERSION = 1
_I8 = np.dtype("<i8")
_F8 = np.dtype("<f8")


class _Block(msgspec.Struct, forbid_unknown_fields=True):
    """One block as it is stored (field names are the map's keys)."""

    version: int
    rows: int
    joints: int
    cycle: bytes
    t: bytes
    log_time_ns: bytes
    position: bytes
    current_reference: bytes
    current: bytes
    setpoint: bytes


_ENCODE = msgspec.msgpack.Encoder().encode
_DECODE = msgspec.msgpack.Decoder(_Block).decode


class ColumnBuffer:
    """The rows written since the last block, in preallocated arrays.

    Parameters
    ----------
    joints
        Number of joints n.
    rows
        Rows per block.
    """

    def __init__(self, joints: int, rows: int = BLOCK_ROWS):
        self.joints = joints
        self.rows = rows
        self.used = 0
        self._cycle = np.empty(rows, dtype=_I8)
        self._t = np.empty(rows, dtype=_F8)
        self._log_time = np.empty(rows, dtype=_I8)
        self._vectors = {name: np.empty((rows, joints), dtype=_F8) for name in VECTOR_FIELDS}

    @property
    def full(self) -> bool:
        """Whether the buffer holds a whole block."""
        return self.used == self.rows

    @property
    def last_log_time_ns(self) -> int:
        """Log time of the last row, ns (the block message's log time)."""
        return int(self._log_time[self.used - 1])

    def append(self, cycle: int, t: float, log_time_ns: int, vectors: dict[str, Any]) -> None:
        """Add one row; ``vectors`` maps each of ``VECTOR_FIELDS`` to n floats or ``None``
        (stored as NaN, as the JSON message's nulls are read; so are non-finite values)."""
        i = self.used
        self._cycle[i] = cycle
        self._t[i] = t
        self._log_time[i] = log_time_ns
        for name, row in self._vectors.items():
            value = vectors[name]
            row[i] = np.nan if value is None else value
        self.used = i + 1

    def take(self) -> bytes:
        """The block of the rows held, encoded; the buffer is then empty."""
        k = self.used
        for v in self._vectors.values():  # JSON stores inf as null, which is read as NaN
            np.copyto(v[:k], np.nan, where=~np.isfinite(v[:k]))
        block = _Block(
            version=VERSION,
            rows=k,
            joints=self.joints,
            cycle=self._cycle[:k].tobytes(),
            t=self._t[:k].tobytes(),
            log_time_ns=self._log_time[:k].tobytes(),
            **{name: v[:k].tobytes() for name, v in self._vectors.items()},
        )
        self.used = 0
        return _ENCODE(block)


def decode_block(data: bytes) -> dict[str, np.ndarray]:
    """The arrays of one block.

    Parameters
    ----------
    data
        A ``/joint_states/columns`` message.

    Returns
    -------
    dict
        ``cycle``, ``log_time_ns`` (int64, shape (k,)), ``t`` (float64, (k,)) and the vector
        fields (float64, (k, n)), read-only views of ``data``.

    Raises
    ------
    ValueError
        Not a block of this version, or arrays whose sizes disagree with ``rows`` and ``joints``.
    """
    try:
        block = _DECODE(data)
    except msgspec.DecodeError as exc:  # ValidationError is a DecodeError
        raise ValueError(f"not a column block ({exc})") from None
    if block.version != VERSION:
        raise ValueError(f"column block version {block.version}, this reader knows {VERSION}")
    k, n = block.rows, block.joints
    if k < 1 or n < 1:
        raise ValueError(f"column block of {k} rows and {n} joints")
    out: dict[str, np.ndarray] = {}
    for name, dtype, shape in (
        ("cycle", _I8, (k,)),
        ("t", _F8, (k,)),
        ("log_time_ns", _I8, (k,)),
        *((name, _F8, (k, n)) for name in VECTOR_FIELDS),
    ):
        raw: bytes = getattr(block, name)
        if len(raw) != int(np.prod(shape)) * 8:
            raise ValueError(f"column block field {name!r} holds {len(raw)} bytes for {shape}")
        out[name] = np.frombuffer(raw, dtype=dtype).reshape(shape)
    return out


#: Every this many ``/joint_states`` messages, one is decoded whole and compared with its row
#: of the blocks (the log times of all of them are compared).
SPOT_EVERY = 64


class ColumnCheck:
    """What the JSON messages of a run must agree with for its blocks to be used in their place.

    The log time of every ``/joint_states`` message is kept (it is in the record header: no
    decoding) and every :data:`SPOT_EVERY`-th message whole; :meth:`disagreement` compares them
    with the rows read from the blocks.

    Parameters
    ----------
    capacity
        Number of ``/joint_states`` messages the file's statistics list.
    """

    def __init__(self, capacity: int):
        self.log_times = np.empty(capacity, dtype=np.int64)
        self.count = 0
        self.spots: dict[int, bytes] = {}

    def add(self, log_times: Sequence[int] | np.ndarray, data_of: Callable[[int], bytes]) -> None:
        """Note a batch of ``/joint_states`` messages in file order: their log times, ns, and
        ``data_of(i)``, the data of the batch's ``i``-th message (called for a few of them).

        Raises
        ------
        ValueError
            More messages than the statistics list, or from ``data_of``.
        """
        start, k = self.count, len(log_times)
        if start + k > self.log_times.size:
            raise ValueError(f"more than the {self.log_times.size} messages listed")
        self.log_times[start : start + k] = log_times
        first = -(-start // SPOT_EVERY) * SPOT_EVERY
        for i in range(first, start + k, SPOT_EVERY):
            self.spots[i] = data_of(i - start)
        self.count = start + k

    def disagreement(self, arrays: dict[str, np.ndarray]) -> str | None:
        """Why the rows in ``arrays`` (file order) do not stand for the JSON messages, or None."""
        rows = arrays["cycle"].shape[0] if arrays else 0
        if rows != self.count:
            return f"{rows} rows in the blocks, {self.count} messages"
        if not np.array_equal(arrays["log_time_ns"], self.log_times[: self.count]):
            i = int(np.flatnonzero(arrays["log_time_ns"] != self.log_times[: self.count])[0])
            return f"log time of message {i}"
        if self.spots and not _same_rows(list(self.spots.values()), arrays, list(self.spots)):
            return "content of a message checked whole"
        return None


def _same_rows(datas: list[bytes], arrays: dict[str, np.ndarray], rows: list[int]) -> bool:
    """Whether the JSON messages ``datas`` read as ``rows`` of ``arrays`` (null as NaN)."""
    try:
        objs = [json.loads(d) for d in datas]
        if not all(type(o["cycle"]) is int and type(o["t"]) in (int, float) for o in objs):
            return False
        if not np.array_equal(np.array([o["cycle"] for o in objs]), arrays["cycle"][rows]):
            return False
        if not np.array_equal(np.array([float(o["t"]) for o in objs]), arrays["t"][rows]):
            return False
        n = arrays["position"].shape[1]
        for name in VECTOR_FIELDS:
            values = [[None] * n if o.get(name) is None else o[name] for o in objs]
            if not all(v is None or type(v) is float or type(v) is int for r in values for v in r):
                return False  # the JSON reader refuses it (booleans, strings...)
            got = np.array(values, dtype=float)  # None -> NaN
            if not np.array_equal(got, arrays[name][rows], equal_nan=True):
                return False
    except (ValueError, TypeError, KeyError, AttributeError, OverflowError, RecursionError):
        return False
    return True
