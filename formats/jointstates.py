"""Decoding ``/joint_states`` messages into columns (contracts.md §4), for :mod:`.logreader`.

Two decoders share one store of preallocated blocks. The batch decoder reads a few thousand
messages at a time with a typed ``msgspec`` decoder and fills whole columns with numpy; it takes
a batch only when every message fits the expected shape. Otherwise the checking decoder reads
that batch one message at a time with ``json`` and names the first fault exactly (message,
cycle, field, joint), so errors are the same whichever decoder would have read the file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from drivegain.errors import DataError
from drivegain.formats.log import REQUIRED_VECTORS, VECTOR_FIELDS

__all__ = ["BATCH", "JointStateParser"]

# Rows per preallocated block when the message count is not known in advance.
_BLOCK_ROWS = 16384
# Messages decoded at a time: large enough for numpy to fill the arrays in bulk, small enough
# that the decoded messages of one batch take little memory.
BATCH = 4096


class _JointState(msgspec.Struct):
    """The typed shape of a ``/joint_states`` message for the fast decoder.

    Other fields (``name``, vendors' additions) are ignored. A message that does not fit this
    shape (null positions, NaN tokens, huge integers, booleans...) is re-read by the checking
    decoder, which names the fault.
    """

    cycle: int
    t: float
    position: list[float]
    current_reference: list[float]
    current: list[float | None] | None = None
    setpoint: list[float | None] | None = None


_DECODE = msgspec.json.Decoder(_JointState).decode


class _Columns:
    """Preallocated blocks of rows for the arrays of a run (no per-message Python objects)."""

    def __init__(self, n: int, capacity: int | None):
        self.n = n
        self.block_rows = capacity if capacity and capacity > 0 else _BLOCK_ROWS
        self.blocks: list[dict[str, np.ndarray]] = []
        self.used = 0  # rows used in the last block
        self.count = 0

    def _new_block(self) -> dict[str, np.ndarray]:
        r, n = self.block_rows, self.n
        block = {
            "cycle": np.empty(r, dtype=np.int64),
            "t": np.empty(r),
            "log_time_ns": np.empty(r, dtype=np.int64),
            **{name: np.empty((r, n)) for name in VECTOR_FIELDS},
        }
        self.blocks.append(block)
        self.used = 0
        return block

    def row(self) -> tuple[dict[str, np.ndarray], int]:
        if not self.blocks or self.used == self.block_rows:
            self._new_block()
        i = self.used
        self.used += 1
        self.count += 1
        return self.blocks[-1], i

    def extend(self, columns: dict[str, np.ndarray], k: int) -> None:
        """Append ``k`` rows given as whole columns (the batch path)."""
        done = 0
        while done < k:
            if not self.blocks or self.used == self.block_rows:
                self._new_block()
            block = self.blocks[-1]
            take = min(k - done, self.block_rows - self.used)
            for name, values in columns.items():
                block[name][self.used : self.used + take] = values[done : done + take]
            self.used += take
            self.count += take
            done += take

    def arrays(self) -> dict[str, np.ndarray]:
        if not self.blocks:
            return {}
        if len(self.blocks) == 1:
            return {k: v[: self.used] for k, v in self.blocks[0].items()}
        parts = [*self.blocks[:-1], {k: v[: self.used] for k, v in self.blocks[-1].items()}]
        out = {}
        for key in parts[0]:
            out[key] = np.concatenate([b[key] for b in parts])
            for b in self.blocks:  # free each block's column as soon as it is copied
                b[key] = np.empty(0)
        return out


def _short(v: Any) -> str:
    """A number for a message: huge integers are cut, not converted (that would overflow)."""
    text = repr(v)
    return text if len(text) <= 24 else f"{text[:12]}...({len(text)} digits)"


def _is_number(v: Any) -> bool:
    # type() rather than isinstance(): JSON true/false must not pass as 1/0
    return type(v) is float or type(v) is int


class JointStateParser:
    """Validates and stores ``/joint_states`` messages one at a time."""

    def __init__(self, path: Path, capacity: int | None):
        self.path = path
        self.capacity = capacity
        self.columns: _Columns | None = None
        self.index = 0

    def error(self, message: str) -> DataError:
        return DataError(message, file=self.path)

    def add_batch(self, datas: list[bytes], log_times: list[int]) -> None:
        """Decode and store messages in bulk; a batch the fast decoder cannot take whole is
        read message by message by :meth:`add`, which names the first fault."""
        columns = self._fast(datas, log_times)
        if columns is None:
            for data, log_time in zip(datas, log_times, strict=True):
                self.add(data, log_time)
            return
        assert self.columns is not None
        self.columns.extend(columns, len(datas))
        self.index += len(datas)

    def add_columns(self, columns: dict[str, np.ndarray]) -> None:
        """Store a block of rows read from ``/joint_states/columns`` (:mod:`.columns`).

        Raises
        ------
        ValueError
            The block's joint count differs from the rows stored before it.
        """
        k, n = columns["position"].shape
        if self.columns is None:
            self.columns = _Columns(n, self.capacity)
        elif n != self.columns.n:
            raise ValueError(f"column block of {n} joints after blocks of {self.columns.n}")
        self.columns.extend(columns, k)
        self.index += k

    def _fast(self, datas: list[bytes], log_times: list[int]) -> dict[str, np.ndarray] | None:
        """The batch as columns, or None when any message needs the checking decoder."""
        k = len(datas)
        if k == 0:
            return None
        try:
            msgs = [_DECODE(d) for d in datas]
        except (msgspec.DecodeError, msgspec.ValidationError, RecursionError):
            return None
        n = self.columns.n if self.columns is not None else len(msgs[0].position)
        if n == 0:
            return None
        try:
            out = {
                "cycle": np.fromiter((m.cycle for m in msgs), dtype=np.int64, count=k),
                "t": np.fromiter((m.t for m in msgs), dtype=float, count=k),
                "log_time_ns": np.fromiter(log_times, dtype=np.int64, count=k),
                "position": np.array([m.position for m in msgs], dtype=float),
                "current_reference": np.array([m.current_reference for m in msgs], dtype=float),
            }
            nan_row = [None] * n  # a null field: NaN, as the checking decoder stores it
            for name in ("current", "setpoint"):
                rows = [getattr(m, name) for m in msgs]
                out[name] = np.array([nan_row if r is None else r for r in rows], dtype=float)
        except (ValueError, OverflowError):  # ragged vectors, integers beyond int64
            return None
        for name in VECTOR_FIELDS:
            if out[name].shape != (k, n) or np.isinf(out[name]).any():
                return None  # the checking decoder says which message and field
        if np.isinf(out["t"]).any():
            return None
        if self.columns is None:
            self.columns = _Columns(n, self.capacity)
        return out

    def add(self, data: bytes, log_time: int) -> None:
        k = self.index
        where = f"/joint_states message {k}"
        try:
            obj = json.loads(data)
        except (ValueError, UnicodeDecodeError, RecursionError) as exc:
            raise self.error(f"{where} is not valid JSON ({exc})") from None
        if not isinstance(obj, dict):
            raise self.error(f"{where} is not a JSON object")
        cycle = obj.get("cycle")
        if type(cycle) is not int:
            raise self.error(f"{where}: field 'cycle' missing or not an integer")
        where = f"/joint_states message {k} (cycle {cycle})"
        t = obj.get("t")
        if not _is_number(t):
            raise self.error(f"{where}: field 't' missing or not a number")
        if self.columns is None:
            pos = obj.get("position")
            if not isinstance(pos, list) or not pos:
                raise self.error(f"{where}: field 'position' missing or not a list")
            self.columns = _Columns(len(pos), self.capacity)
        n = self.columns.n
        block, i = self.columns.row()
        for name, value in (("cycle", cycle), ("t", t), ("log_time_ns", log_time)):
            try:
                block[name][i] = value
            except OverflowError:
                raise self.error(
                    f"{where}: field '{name}' is out of range: {_short(value)}"
                ) from None
        for name in VECTOR_FIELDS:
            values = obj.get(name)
            if values is None and name not in REQUIRED_VECTORS:
                block[name][i] = np.nan
                continue
            if not isinstance(values, list):
                raise self.error(f"{where}: field '{name}' missing or not a list")
            if len(values) != n:
                raise self.error(
                    f"{where}: field '{name}' has {len(values)} values, expected {n} joints"
                )
            row = block[name][i]
            if all(type(v) is float or type(v) is int for v in values):
                try:
                    row[:] = values
                    continue
                except OverflowError:
                    pass  # found below, element by element
            for j, v in enumerate(values):
                if v is None:
                    row[j] = np.nan
                elif not _is_number(v):
                    raise self.error(f"{where}: {name}[{j}] is not a number: {v!r}")
                else:
                    try:
                        row[j] = v
                    except OverflowError:
                        raise self.error(
                            f"{where}: {name}[{j}] is out of range: {_short(v)}"
                        ) from None
        self.index += 1
