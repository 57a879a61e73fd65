"""Reading the acquisition log (contracts.md §4).

:func:`read_run` accepts any program's file that follows §4 (only ``/joint_states`` and the
``drivegain.run`` metadata are needed) and a ``.part`` whose writer was killed: it returns every
complete message and says how many it recovered. Records are read by :mod:`.mcapscan` (no object
per message) and ``/joint_states`` messages are decoded a batch at a time by :mod:`.jointstates`
into preallocated arrays, so memory stays at about the size of the arrays returned.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.reader import SeekingReader
from mcap.records import Attachment, Channel, Footer, Metadata

from drivegain.errors import DataError
from drivegain.fileio import reading
from drivegain.formats.columns import ColumnCheck, decode_block
from drivegain.formats.jointstates import BATCH, JointStateParser
from drivegain.formats.log import (
    EVENTS,
    FORMAT_VERSION,
    JOINT_STATE_COLUMNS,
    JOINT_STATES,
    METADATA_NAME,
    REQUIRED_KEYS,
    REQUIRED_VECTORS,
    VECTOR_FIELDS,
)
from drivegain.formats.mcapscan import FILLED, Buckets, IndexedChunk, records

_MCAP_MAGIC = b"\x89MCAP0\r\n"
# Channel kinds collected while reading (mcapscan buckets).
_JS, _EV, _COL = 1, 2, 3
_log = logging.getLogger(__name__)


class _ColumnsUnusable(Exception):
    """The ``/joint_states/columns`` blocks cannot stand for the JSON messages (why)."""


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


@dataclass(frozen=True)
class _Listing:
    """What a finished file's summary says: message counts per topic, the channels, and
    whether every chunk has message indexes."""

    counts: dict[str, int]
    channels: list[Channel]
    indexed: bool


def _summary_listing(fh: IO[bytes], size: int) -> _Listing | None:
    """What a finished file's summary lists, else None."""
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
    counts = summary.statistics.channel_message_counts
    listed: dict[str, int] = {}
    for c in summary.channels.values():
        listed[c.topic] = listed.get(c.topic, 0) + counts.get(c.id, 0)
    chunks = summary.chunk_indexes
    indexed = bool(chunks) and all(c.message_index_length > 0 for c in chunks)
    return _Listing(listed, list(summary.channels.values()), indexed)


def _finished(fh: IO[bytes], size: int) -> bool:
    """Whether the file ends with the MCAP closing magic (its writer finished it)."""
    if size < 2 * len(_MCAP_MAGIC):
        return False
    fh.seek(size - len(_MCAP_MAGIC))
    try:
        return fh.read(len(_MCAP_MAGIC)) == _MCAP_MAGIC
    finally:
        fh.seek(0)


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
    with reading(p, error=DataError, expected="an MCAP file"):
        fh = open(p, "rb")
    with fh:
        size = os.fstat(fh.fileno()).st_size
        if size == 0:
            raise DataError("empty file, expected an MCAP log", file=p)
        if fh.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
            raise DataError("not an MCAP file (bad magic bytes)", file=p)
        fh.seek(0)
        try:
            return _read_stream(fh, size, p, n_joints, columns=True)
        except _ColumnsUnusable as exc:
            # The JSON messages are the contract: read them (a second pass, for a file another
            # program changed after drivegain wrote it).
            _log.warning(
                "%s: %s disagrees with %s (%s); reading the JSON messages",
                p,
                JOINT_STATE_COLUMNS,
                JOINT_STATES,
                exc,
            )
            return _read_stream(fh, size, p, n_joints, columns=False)


def _read_stream(
    fh: IO[bytes], size: int, p: Path, n_joints: int | None, *, columns: bool
) -> RunLog:
    finished = _finished(fh, size)
    listing = _summary_listing(fh, size)
    counts = None if listing is None else listing.counts
    listed = None if counts is None else counts.get(JOINT_STATES, 0)
    # A message takes more than 16 bytes even compressed: a larger count is not to be trusted.
    capacity = None if listed is None else (min(listed, size // 16) or None)
    parser = JointStateParser(p, capacity)
    # A finished file with blocks on the side channel is read from them (formats/columns.py);
    # the JSON messages are then only checked against them, not decoded.
    check = (
        ColumnCheck(capacity)
        if columns and capacity and counts and counts.get(JOINT_STATE_COLUMNS, 0) > 0
        else None
    )
    meta: dict[str, str] | None = None
    attachments: dict[str, bytes] = {}
    channels: dict[int, Channel] = {}
    footer = False
    buckets: Buckets = {_JS: ([], []), _EV: ([], []), _COL: ([], [])}
    states = buckets[_JS]
    classify = partial(_classify, p, check is not None)
    indexed = None
    if check is not None and listing is not None and listing.indexed:
        # chunks are then read through their message indexes: no loop over every message
        kinds = {c.id: classify(c) for c in listing.channels}
        indexed = {i: kind for i, kind in kinds.items() if kind is not None}
    for record in records(fh, size, p, finished, classify, buckets, indexed):
        if isinstance(record, IndexedChunk):
            assert check is not None
            _take_chunk(check, parser, record, buckets[_EV])
        elif record is FILLED:
            if check is not None:
                _take_blocks(check, parser, states, buckets[_COL])
            elif len(states[0]) >= BATCH:
                parser.add_batch(states[0], states[1])
                states[0].clear()
                states[1].clear()
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Metadata):
            if record.name == METADATA_NAME and meta is None:
                meta = dict(record.metadata)
        elif isinstance(record, Attachment):
            attachments[record.name] = bytes(record.data)
        elif isinstance(record, Footer):
            footer = True
    fast: dict[str, np.ndarray] | None = None
    if check is None:
        parser.add_batch(states[0], states[1])
    else:
        fast = parser.columns.arrays() if parser.columns is not None else {}
        why = check.disagreement(fast)
        if why is not None:
            raise _ColumnsUnusable(why)
    events = [_event(data, log_time) for data, log_time in zip(*buckets[_EV], strict=True)]
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
    arrays = cols.arrays() if fast is None else fast
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


def _take_blocks(
    check: ColumnCheck,
    parser: JointStateParser,
    states: tuple[list[bytes], list[int]],
    blocks: tuple[list[bytes], list[int]],
) -> None:
    """Note the JSON messages read so far in ``check`` and store the blocks' rows."""
    try:
        check.add(states[1], states[0].__getitem__)
        for data in blocks[0]:
            parser.add_columns(decode_block(data))
    except ValueError as exc:
        raise _ColumnsUnusable(str(exc)) from None
    for bucket in (states, blocks):
        bucket[0].clear()
        bucket[1].clear()


def _take_chunk(
    check: ColumnCheck,
    parser: JointStateParser,
    chunk: IndexedChunk,
    events: tuple[list[bytes], list[int]],
) -> None:
    """Note a chunk's JSON messages in ``check``, store its blocks' rows, keep its events."""
    try:
        if chunk.damaged is not None:
            raise ValueError(chunk.damaged)
        js = chunk.entries.get(_JS)
        if js is not None:
            check.add(js[:, 0], lambda i: chunk.message(_JS, int(js[i, 1]), int(js[i, 0])))
        for log_time, offset in chunk.entries.get(_COL, ()):
            parser.add_columns(decode_block(chunk.message(_COL, int(offset), int(log_time))))
        for log_time, offset in chunk.entries.get(_EV, ()):
            events[0].append(chunk.message(_EV, int(offset), int(log_time)))
            events[1].append(int(log_time))
    except ValueError as exc:
        raise _ColumnsUnusable(str(exc)) from None


def _classify(p: Path, columns: bool, channel: Channel) -> int | None:
    """The bucket a channel's messages go to (None: not read); ``columns``: whether the
    ``/joint_states/columns`` blocks are read."""
    if channel.topic == JOINT_STATES:
        if channel.message_encoding != "json":
            raise DataError(
                f"channel {JOINT_STATES} has message encoding "
                f"'{channel.message_encoding}', expected 'json'",
                file=p,
            )
        return _JS
    if channel.topic == EVENTS and channel.message_encoding == "json":
        return _EV
    if columns and channel.topic == JOINT_STATE_COLUMNS and channel.message_encoding == "msgpack":
        return _COL
    return None


def _event(data: bytes, log_time: int) -> dict[str, Any]:
    try:
        ev = json.loads(data)
    except (ValueError, RecursionError):
        ev = {"text": "(undecodable event)"}
    if not isinstance(ev, dict):
        ev = {"text": str(ev)}
    ev["log_time_ns"] = log_time
    return ev


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
        buckets: Buckets = {_JS: ([], [])}
        datas, times = buckets[_JS]
        finished = _finished(fh, size)
        for record in records(fh, size, p, finished, partial(_of_topic, topic), buckets):
            if record is not FILLED:
                continue
            for log_time, data in zip(times, datas, strict=True):
                try:
                    yield log_time, json.loads(data)
                except (ValueError, RecursionError) as exc:
                    text = f"a {topic} message at log time {log_time} ns is not JSON"
                    raise DataError(f"{text} ({type(exc).__name__})", file=p) from None
            datas.clear()
            times.clear()


def _of_topic(topic: str, channel: Channel) -> int | None:
    return _JS if channel.topic == topic else None
