"""Reading the acquisition log (contracts.md §4).

:func:`read_run` accepts any program's file that follows §4 (only ``/joint_states`` and the
``drivegain.run`` metadata are needed) and a ``.part`` whose writer was killed: it returns every
complete message and says how many it recovered. Messages are streamed record by record into
preallocated arrays, so memory stays at about the size of the arrays returned.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.reader import SeekingReader
from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from drivegain.errors import DataError
from drivegain.formats.log import (
    EVENTS,
    FORMAT_VERSION,
    JOINT_STATES,
    METADATA_NAME,
    REQUIRED_KEYS,
    REQUIRED_VECTORS,
    VECTOR_FIELDS,
)

_MCAP_MAGIC = b"\x89MCAP0\r\n"
# Rows per preallocated block when the message count is not known in advance.
_BLOCK_ROWS = 16384


@dataclass
class RunLog:
    """One run as read from a log file.

    Attributes
    ----------
    path
        The file read.
    meta
        The ``drivegain.run`` metadata record (all strings).
    joint_names, sync_period_s
        Parsed from the metadata.
    cycle
        SYNC cycle indices, (N,) int64, strictly increasing.
    t
        Seconds since the first cycle, (N,), strictly increasing.
    position
        Joint positions, rad, (N, n).
    current_reference
        Current references, A (or what the metadata ``current_unit`` says), (N, n).
    current
        Measured currents, A, (N, n); NaN where the file holds null (not measured).
    setpoint
        Commanded positions, rad, (N, n); NaN where unknown.
    events
        ``/events`` messages as dicts, each with ``log_time_ns`` added.
    attachments
        Attachment name -> bytes.
    truncated
        True when the file ends before the MCAP footer (a writer killed mid-run).
    messages_recovered
        Number of ``/joint_states`` messages read.
    log_time_ns
        Log time of each ``/joint_states`` message, ns, (N,).
    """

    path: Path
    meta: dict[str, str]
    joint_names: list[str]
    sync_period_s: float
    cycle: np.ndarray
    t: np.ndarray
    position: np.ndarray
    current_reference: np.ndarray
    current: np.ndarray
    setpoint: np.ndarray
    events: list[dict[str, Any]]
    attachments: dict[str, bytes]
    truncated: bool
    messages_recovered: int
    log_time_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def n(self) -> int:
        """Number of joints."""
        return len(self.joint_names)

    @property
    def rate_hz(self) -> float:
        """Nominal sample rate, Hz (1 / SYNC period)."""
        return 1.0 / self.sync_period_s

    def missing_cycles(self) -> int:
        """Number of SYNC cycles absent between the first and the last message."""
        if self.cycle.size == 0:
            return 0
        return int(self.cycle[-1] - self.cycle[0] + 1 - self.cycle.size)


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


class _JointStateParser:
    """Validates and stores ``/joint_states`` messages one at a time."""

    def __init__(self, path: Path, capacity: int | None):
        self.path = path
        self.capacity = capacity
        self.columns: _Columns | None = None
        self.index = 0

    def error(self, message: str) -> DataError:
        return DataError(message, file=self.path)

    def add(self, msg: Message) -> None:
        k = self.index
        where = f"/joint_states message {k}"
        try:
            obj = json.loads(msg.data)
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
        for name, value in (("cycle", cycle), ("t", t), ("log_time_ns", msg.log_time)):
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


def _listed_messages(fh: IO[bytes], size: int) -> int | None:
    """Number of ``/joint_states`` messages in a finished file's statistics, else None."""
    if not _finished(fh, size):
        return None  # no closing magic: cut file, no summary
    try:
        summary = SeekingReader(fh).get_summary()
    except Exception:  # an odd summary is not needed to read the messages: grow by blocks
        return None
    finally:
        fh.seek(0)
    if summary is None or summary.statistics is None:
        return None
    ids = [c.id for c in summary.channels.values() if c.topic == JOINT_STATES]
    counts = summary.statistics.channel_message_counts
    return sum(counts.get(i, 0) for i in ids)


def _finished(fh: IO[bytes], size: int) -> bool:
    """Whether the file ends with the MCAP closing magic (its writer finished it)."""
    if size < 2 * len(_MCAP_MAGIC):
        return False
    fh.seek(size - len(_MCAP_MAGIC))
    try:
        return fh.read(len(_MCAP_MAGIC)) == _MCAP_MAGIC
    finally:
        fh.seek(0)


def _iter_records(fh: IO[bytes], size: int, path: Path, finished: bool) -> Iterator[Any]:
    """Records in file order; stops quietly at a cut (the reader can tell by the missing footer).

    A file that ends with the closing magic was finished by its writer: a record that fails to
    parse there is corruption, wherever it is (a corrupt record length can send the reader to
    the end of the file). In a file without the closing magic, a failure at the end of the file
    is the cut of a killed writer; anywhere else it is corruption.
    """
    reader = StreamReader(fh, validate_crcs=True)
    records = reader.records
    while True:
        try:
            record = next(records)
        except StopIteration:
            return
        except Exception as exc:  # McapError, struct.error, zstd errors... from a record cut short
            if fh.tell() >= size and not finished:
                return
            raise DataError(
                f"corrupt MCAP data at byte {fh.tell()} of {size} ({type(exc).__name__}: {exc})",
                file=path,
            ) from None
        yield record


def read_run(path: str | Path, n_joints: int | None = None) -> RunLog:
    """Read a run log (complete ``.mcap`` or the ``.part`` of a killed writer).

    Parameters
    ----------
    path
        The MCAP file.
    n_joints
        If given, the number of joints the caller's robot has; a log with another count is an
        error.

    Returns
    -------
    RunLog
        Arrays ordered by log time; ``truncated`` and ``messages_recovered`` say how much of a
        cut file was read.

    Raises
    ------
    DataError
        One line naming the file: not found, empty, not MCAP, corrupt, no ``drivegain.run``
        metadata or missing keys, no ``/joint_states`` channel or messages, wrong joint count,
        malformed message, non-monotonic time or cycle, NaN/inf in positions or current
        references.
    """
    p = Path(path)
    try:
        fh = open(p, "rb")
    except FileNotFoundError:
        raise DataError("file not found", file=p) from None
    except IsADirectoryError:
        raise DataError("is a directory, expected an MCAP file", file=p) from None
    except OSError as exc:
        raise DataError(f"cannot open: {exc.strerror}", file=p) from None
    with fh:
        size = os.fstat(fh.fileno()).st_size
        if size == 0:
            raise DataError("empty file, expected an MCAP log", file=p)
        if fh.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
            raise DataError("not an MCAP file (bad magic bytes)", file=p)
        fh.seek(0)
        return _read_stream(fh, size, p, n_joints)


def _read_stream(fh: IO[bytes], size: int, p: Path, n_joints: int | None) -> RunLog:
    finished = _finished(fh, size)
    listed = _listed_messages(fh, size)
    # A message takes more than 16 bytes even compressed: a larger count is not to be trusted.
    capacity = None if listed is None else (min(listed, size // 16) or None)
    parser = _JointStateParser(p, capacity)
    meta: dict[str, str] | None = None
    attachments: dict[str, bytes] = {}
    events: list[dict[str, Any]] = []
    channels: dict[int, Channel] = {}
    footer = False
    for record in _iter_records(fh, size, p, finished):
        if isinstance(record, Message):
            ch = channels.get(record.channel_id)
            if ch is None:
                continue
            if ch.topic == JOINT_STATES:
                parser.add(record)
            elif ch.topic == EVENTS and ch.message_encoding == "json":
                try:
                    ev = json.loads(record.data)
                except (ValueError, RecursionError):
                    ev = {"text": "(undecodable event)"}
                if not isinstance(ev, dict):
                    ev = {"text": str(ev)}
                ev["log_time_ns"] = record.log_time
                events.append(ev)
        elif isinstance(record, Channel):
            if record.topic == JOINT_STATES and record.message_encoding != "json":
                raise DataError(
                    f"channel {JOINT_STATES} has message encoding "
                    f"'{record.message_encoding}', expected 'json'",
                    file=p,
                )
            channels[record.id] = record
        elif isinstance(record, Metadata):
            if record.name == METADATA_NAME and meta is None:
                meta = dict(record.metadata)
        elif isinstance(record, Attachment):
            attachments[record.name] = bytes(record.data)
        elif isinstance(record, Footer):
            footer = True
        elif isinstance(record, Schema):
            pass
    truncated = not footer
    if finished and truncated:
        raise DataError(
            f"ends with the MCAP closing magic but its footer was not reached: corrupt data "
            f"before byte {size}",
            file=p,
        )
    cut = f" (file ends at byte {size}: the writer did not finish)" if truncated else ""

    if meta is None:
        raise DataError(f"no metadata record '{METADATA_NAME}'{cut}", file=p)
    missing = [k for k in REQUIRED_KEYS if k not in meta]
    if missing:
        raise DataError(
            f"metadata record '{METADATA_NAME}' lacks keys: {', '.join(missing)}", file=p
        )
    if meta["format_version"] != FORMAT_VERSION:
        raise DataError(
            f"unsupported format_version {meta['format_version']!r} (this reader knows "
            f"{FORMAT_VERSION!r})",
            file=p,
        )
    joint_names = _joint_names(meta["joint_names"], p)
    period = _positive_float(meta["sync_period_s"], "sync_period_s", p)
    if n_joints is not None and len(joint_names) != n_joints:
        raise DataError(
            f"log has {len(joint_names)} joints ({', '.join(joint_names)}), the robot has "
            f"{n_joints}",
            file=p,
        )
    cols = parser.columns
    if cols is None or cols.count == 0:
        if truncated:
            raise DataError(
                f"no complete {JOINT_STATES} message to recover: the file ends at byte {size}, "
                "before the writer's first flush (it did not finish)",
                file=p,
            )
        if not any(c.topic == JOINT_STATES for c in channels.values()):
            topics = sorted({c.topic for c in channels.values()})
            have = f"channels present: {', '.join(topics)}" if topics else "no channels"
            raise DataError(f"missing channel {JOINT_STATES} ({have})", file=p)
        raise DataError(f"no messages on {JOINT_STATES} (empty run)", file=p)
    if cols.n != len(joint_names):
        raise DataError(
            f"{JOINT_STATES} messages carry {cols.n} joints, metadata joint_names has "
            f"{len(joint_names)}",
            file=p,
        )
    count = cols.count
    if listed is not None and not truncated and count != listed:
        raise DataError(
            f"its statistics list {listed} {JOINT_STATES} messages, {count} could be read: "
            "the file is corrupt",
            file=p,
        )
    arrays = cols.arrays()
    _order_by_log_time(arrays)
    _check_monotonic(arrays, p)
    _check_finite(arrays, joint_names, p)
    return RunLog(
        path=p,
        meta=meta,
        joint_names=joint_names,
        sync_period_s=period,
        cycle=arrays["cycle"],
        t=arrays["t"],
        position=arrays["position"],
        current_reference=arrays["current_reference"],
        current=arrays["current"],
        setpoint=arrays["setpoint"],
        events=sorted(events, key=lambda e: int(e["log_time_ns"])),
        attachments=attachments,
        truncated=truncated,
        messages_recovered=count,
        log_time_ns=arrays["log_time_ns"],
    )


def _joint_names(text: str, p: Path) -> list[str]:
    try:
        names = json.loads(text)
    except ValueError:
        names = None
    if (
        not isinstance(names, list)
        or not names
        or not all(isinstance(x, str) for x in names)
        or len(set(names)) != len(names)
    ):
        raise DataError(
            f"metadata 'joint_names' must be a JSON list of unique strings, got {text!r}", file=p
        )
    return names


def _positive_float(text: str, key: str, p: Path) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise DataError(f"metadata '{key}' must be a positive number, got {text!r}", file=p)
    return value


def _order_by_log_time(arrays: dict[str, np.ndarray]) -> None:
    """Put messages in log-time order, as MCAP readers do (a writer may interleave chunks)."""
    lt = arrays["log_time_ns"]
    if lt.size < 2 or bool(np.all(lt[1:] >= lt[:-1])):
        return
    order = np.argsort(lt, kind="stable")
    for key in arrays:
        arrays[key] = arrays[key][order]


def _check_monotonic(arrays: dict[str, np.ndarray], p: Path) -> None:
    if not np.isfinite(arrays["t"]).all():
        k = int(np.flatnonzero(~np.isfinite(arrays["t"]))[0])
        raise DataError(f"{JOINT_STATES} message {k}: 't' is not finite", file=p)
    for key, unit in (("cycle", ""), ("t", " s")):
        v = arrays[key]
        bad = np.flatnonzero(~(v[1:] > v[:-1]))
        if bad.size:
            k = int(bad[0]) + 1
            raise DataError(
                f"{JOINT_STATES}: '{key}' not strictly increasing at message {k} "
                f"(cycle {int(arrays['cycle'][k])}): {v[k - 1]}{unit} then {v[k]}{unit}",
                file=p,
            )


#: Largest magnitude a logged position (rad) or current (A) may have. Far beyond any joint or
#: drive (10⁶ rad is 160 000 turns), small enough that squares and differences of the values
#: stay finite in the filters: a corrupt 1e300 is refused here, not met as an overflow later.
PLAUSIBLE_MAGNITUDE = 1e6


def _check_finite(arrays: dict[str, np.ndarray], joint_names: list[str], p: Path) -> None:
    for name in VECTOR_FIELDS:
        values = arrays[name]
        required = name in REQUIRED_VECTORS
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(values) if required else np.abs(values) > PLAUSIBLE_MAGNITUDE
            bad |= np.abs(values) > PLAUSIBLE_MAGNITUDE
        if not bad.any():
            continue
        k, j = (int(x) for x in np.argwhere(bad)[0])
        n_bad = int(bad.any(axis=1).sum())
        v = values[k, j]
        what = (
            "is not finite (NaN, inf or null)"
            if not np.isfinite(v)
            else f"is {v:.6g}, beyond any plausible value (|x| <= {PLAUSIBLE_MAGNITUDE:g})"
        )
        raise DataError(
            f"{JOINT_STATES} message {k} (cycle {int(arrays['cycle'][k])}): "
            f"{name} of joint {joint_names[j]} {what}; {n_bad} message(s) affected",
            file=p,
        )


def iter_channel(path: str | Path, topic: str) -> Iterator[tuple[int, dict[str, Any]]]:
    """Decoded JSON messages of one channel in file order, as ``(log_time_ns, message)``.

    For channels :func:`read_run` does not load (``/drives/raw``); tolerates a cut file.
    """
    p = Path(path)
    with open(p, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if fh.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
            raise DataError("not an MCAP file (bad magic bytes)", file=p)
        fh.seek(0)
        channels: dict[int, str] = {}
        for record in _iter_records(fh, size, p, _finished(fh, size)):
            if isinstance(record, Channel):
                channels[record.id] = record.topic
            elif isinstance(record, Message) and channels.get(record.channel_id) == topic:
                try:
                    yield record.log_time, json.loads(record.data)
                except (ValueError, RecursionError) as exc:
                    text = f"a {topic} message at log time {record.log_time} ns is not JSON"
                    raise DataError(f"{text} ({type(exc).__name__})", file=p) from None
