"""The acquisition log: MCAP files per contracts.md §4 (``format_version`` 1).

Writing: :class:`LogWriter` streams one run to ``NAME.mcap.part`` (zstd chunks of 1 MiB) and
renames it to ``NAME.mcap`` when :meth:`LogWriter.finish` is called. The metadata record and the
attachments are written and flushed first, so even a writer killed in its first second leaves a
file that says what it was recording.

Reading: :func:`read_run` accepts any program's file that follows §4 (only ``/joint_states`` and
the ``drivegain.run`` metadata are needed) and a ``.part`` whose writer was killed: it returns
every complete message and says how many it recovered. Messages are streamed record by record
into preallocated arrays, so memory stays at about the size of the arrays returned.

Every problem with a file is a :class:`~drivegain.errors.DataError` whose one-line message names
the file and, where it applies, the message, cycle, field and joint.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np
from mcap.reader import SeekingReader
from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from drivegain import __version__
from drivegain.errors import DataError

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

_MCAP_MAGIC = b"\x89MCAP0\r\n"
# Rows per preallocated block when the message count is not known in advance.
_BLOCK_ROWS = 16384


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
            raise ValueError(f"joint_names must be unique and non-empty, got {self.joint_names}")
        if not (math.isfinite(self.sync_period_s) and self.sync_period_s > 0):
            raise ValueError(f"sync_period_s must be positive, got {self.sync_period_s}")
        clash = set(self.extra) & set(REQUIRED_KEYS)
        if clash:
            raise ValueError(f"extra metadata reuses reserved keys {sorted(clash)}")
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in self.extra.items()):
            raise ValueError("extra metadata keys and values must be strings")

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


_RAW_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "drivegain.DrivesRaw",
    "description": "raw values as the drives sent them in one SYNC cycle, keyed by node",
    "type": "object",
    "properties": {"cycle": {"type": "integer"}, "raw": {"type": "object"}},
    "required": ["cycle", "raw"],
}

_EVENT_SCHEMA: dict[str, Any] = {
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


def _json_bytes(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False, default=str).encode()


def _vector(value: Any, n: int, name: str) -> list[float | None]:
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.size != n:
        raise ValueError(f"{name} has {arr.size} values, the log has {n} joints")
    out: list[float | None] = arr.tolist()
    if not np.isfinite(arr).all():
        # JSON has no NaN: a non-finite value is stored as null, which readers reject where
        # the value is needed.
        out = [v if v is not None and math.isfinite(v) else None for v in out]
    return out


class LogWriter:
    """Writes one run to ``NAME.mcap.part``; :meth:`finish` renames it to ``NAME.mcap``.

    Not thread-safe: one thread (the recorder's writer thread) owns it.

    Parameters
    ----------
    path
        The final file name (``NAME.mcap``); the file being written is ``path`` + ``.part``.
    meta
        The run's metadata record.
    attachments
        ``(name, media_type, data)`` stored byte for byte (robot TOML, payload TOML, trajectory).
    chunk_size
        Uncompressed chunk size, bytes.

    Raises
    ------
    DataError
        If the ``.part`` file cannot be created.
    """

    def __init__(
        self,
        path: str | Path,
        meta: RunMetadata,
        attachments: Sequence[tuple[str, str, bytes]] = (),
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
    ):
        self.path = Path(path)
        self.part_path = self.path.with_name(self.path.name + ".part")
        self.meta = meta
        self._n = len(meta.joint_names)
        try:
            self._file: IO[bytes] = open(self.part_path, "wb")
        except OSError as exc:
            raise DataError(
                f"cannot create log file: {exc.strerror}", file=self.part_path
            ) from None
        self._done = False
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=f"drivegain {__version__}")
        self._writer.add_metadata(METADATA_NAME, meta.to_record())
        now = time.time_ns()
        for name, media_type, data in attachments:
            self._writer.add_attachment(
                create_time=now, log_time=now, name=name, media_type=media_type, data=bytes(data)
            )
        js = self._writer.register_schema(
            "drivegain.JointState", "jsonschema", _json_bytes(joint_state_schema(meta.joint_names))
        )
        rs = self._writer.register_schema(
            "drivegain.DrivesRaw", "jsonschema", _json_bytes(_RAW_SCHEMA)
        )
        es = self._writer.register_schema(
            "drivegain.Event", "jsonschema", _json_bytes(_EVENT_SCHEMA)
        )
        self._joint_states = self._writer.register_channel(JOINT_STATES, "json", js)
        self._raw = self._writer.register_channel(RAW, "json", rs)
        self._events = self._writer.register_channel(EVENTS, "json", es)
        self._sequence = {self._joint_states: 0, self._raw: 0, self._events: 0}
        self.messages = 0
        self.flush()

    def _add(self, channel: int, log_time_ns: int, data: bytes) -> None:
        if self._done:
            raise RuntimeError(f"{self.part_path}: log already finished or closed")
        if log_time_ns < 0:
            raise ValueError(f"log time must be >= 0 ns, got {log_time_ns}")
        seq = self._sequence[channel]
        self._sequence[channel] = seq + 1
        self._writer.add_message(
            channel_id=channel,
            log_time=int(log_time_ns),
            data=data,
            publish_time=int(log_time_ns),
            sequence=seq & 0xFFFFFFFF,
        )
        self.messages += 1

    def write_joint_state(
        self,
        *,
        cycle: int,
        t: float,
        log_time_ns: int,
        position: Any,
        current_reference: Any,
        current: Any | None,
        setpoint: Any | None,
    ) -> None:
        """Append one SYNC cycle to ``/joint_states``.

        Parameters
        ----------
        cycle
            SYNC cycle index since the start of the run (no wrap).
        t
            Seconds since the first cycle.
        log_time_ns
            SYNC time, ns.
        position
            Joint positions, rad (joint side, controller convention), n values.
        current_reference
            Current reference of each drive, A, n values.
        current
            Measured current of each drive, A, or ``None`` when not measured (stored as nulls).
        setpoint
            Commanded joint positions, rad, or ``None`` when unknown (stored as nulls).
        """
        n = self._n
        nulls: list[float | None] = [None] * n
        msg = {
            "cycle": int(cycle),
            "t": float(t),
            "position": _vector(position, n, "position"),
            "current_reference": _vector(current_reference, n, "current_reference"),
            "current": nulls if current is None else _vector(current, n, "current"),
            "setpoint": nulls if setpoint is None else _vector(setpoint, n, "setpoint"),
        }
        self._add(self._joint_states, log_time_ns, _json_bytes(msg))

    def write_raw(self, *, cycle: int, log_time_ns: int, raw: Mapping[str, Any]) -> None:
        """Append the raw drive values of one cycle to ``/drives/raw`` (JSON-serialisable)."""
        self._add(self._raw, log_time_ns, _json_bytes({"cycle": int(cycle), "raw": dict(raw)}))

    def write_event(
        self,
        *,
        log_time_ns: int,
        level: str,
        node: int | None,
        code: int | None,
        text: str,
        **fields: Any,
    ) -> None:
        """Append one event to ``/events``; extra ``fields`` are stored beside the four keys."""
        clash = set(fields) & {"level", "node", "code", "text"}
        if clash:
            raise ValueError(f"event fields reuse reserved keys {sorted(clash)}")
        msg = {
            "level": str(level),
            "node": None if node is None else int(node),
            "code": None if code is None else int(code),
            "text": str(text),
            **fields,
        }
        self._add(self._events, log_time_ns, _json_bytes(msg))

    def flush(self) -> None:
        """Close the open chunk and force everything written so far to disk (flush + fsync).

        What has been flushed survives the process being killed.
        """
        if self._done:
            return
        self._writer.flush()
        self._file.flush()
        os.fsync(self._file.fileno())

    def finish(self) -> Path:
        """Finish the MCAP (indexes, summary), fsync, rename ``.part`` to the final name.

        Returns
        -------
        pathlib.Path
            The final path.
        """
        if self._done:
            if self.part_path.exists():
                raise RuntimeError(f"{self.part_path}: log was closed unfinished")
            return self.path
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        self._done = True
        os.replace(self.part_path, self.path)
        _fsync_dir(self.path.parent)
        return self.path

    def close_unfinished(self) -> None:
        """Close the file without finishing it: the ``.part`` stays, as after a crash.

        Messages since the last :meth:`flush` (the open chunk) are lost, as they would be.
        """
        if self._done:
            return
        self._done = True
        try:
            self._file.close()
        except OSError:
            pass

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        # Even after a fault the log of everything up to it is complete and worth finishing.
        try:
            self.finish()
        except Exception:
            self.close_unfinished()
            if exc is None:
                raise


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_run(
    path: str | Path,
    meta: RunMetadata,
    t: np.ndarray,
    position: np.ndarray,
    current_reference: np.ndarray,
    current: np.ndarray | None = None,
    setpoint: np.ndarray | None = None,
    *,
    cycle: np.ndarray | None = None,
    log_time_ns: np.ndarray | None = None,
    attachments: Sequence[tuple[str, str, bytes]] = (),
    events: Sequence[Mapping[str, Any]] = (),
) -> Path:
    """Write a whole run log at once (for tests, synthetic data and converters).

    Parameters
    ----------
    path
        Final ``.mcap`` path (written as ``.part`` and renamed).
    meta
        Metadata record.
    t
        Seconds since the first cycle, shape (N,).
    position, current_reference, current, setpoint
        Shape (N, n); ``current`` and ``setpoint`` may be ``None`` (stored as nulls).
    cycle
        Cycle indices (default ``0..N-1``).
    log_time_ns
        Log times, ns (default ``round(t·1e9)``).
    attachments
        ``(name, media_type, data)``.
    events
        Event dicts with ``log_time_ns``, ``level``, ``node``, ``code``, ``text`` and any more
        keys.

    Returns
    -------
    pathlib.Path
        The final path. On any error the ``.part`` is removed.
    """
    t = np.asarray(t, dtype=float)
    pos = np.asarray(position, dtype=float)
    ref = np.asarray(current_reference, dtype=float)
    cur = None if current is None else np.asarray(current, dtype=float)
    sp = None if setpoint is None else np.asarray(setpoint, dtype=float)
    n_samples = t.shape[0]
    for name, arr in (
        ("position", pos),
        ("current_reference", ref),
        ("current", cur),
        ("setpoint", sp),
    ):
        if arr is not None and arr.shape[0] != n_samples:
            raise ValueError(f"{name} has {arr.shape[0]} samples, t has {n_samples}")
    cyc = np.arange(n_samples) if cycle is None else np.asarray(cycle, dtype=np.int64)
    lt = np.rint(t * 1e9).astype(np.int64) if log_time_ns is None else np.asarray(log_time_ns)
    writer = LogWriter(path, meta, attachments)
    try:
        ev = sorted(events, key=lambda e: int(e["log_time_ns"]))
        k = 0
        for i in range(n_samples):
            while k < len(ev) and int(ev[k]["log_time_ns"]) <= lt[i]:
                _write_event_dict(writer, ev[k])
                k += 1
            writer.write_joint_state(
                cycle=int(cyc[i]),
                t=float(t[i]),
                log_time_ns=int(lt[i]),
                position=pos[i],
                current_reference=ref[i],
                current=None if cur is None else cur[i],
                setpoint=None if sp is None else sp[i],
            )
        for e in ev[k:]:
            _write_event_dict(writer, e)
        return writer.finish()
    except BaseException:
        writer.close_unfinished()
        writer.part_path.unlink(missing_ok=True)
        raise


def _write_event_dict(writer: LogWriter, e: Mapping[str, Any]) -> None:
    extra = {
        k: v for k, v in e.items() if k not in ("log_time_ns", "level", "node", "code", "text")
    }
    writer.write_event(
        log_time_ns=int(e["log_time_ns"]),
        level=str(e.get("level", "info")),
        node=e.get("node"),
        code=e.get("code"),
        text=str(e.get("text", "")),
        **extra,
    )


# --------------------------------------------------------------------------------------------
# Reading


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
        except (ValueError, UnicodeDecodeError) as exc:
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
        block["cycle"][i] = cycle
        block["t"][i] = t
        block["log_time_ns"][i] = msg.log_time
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
                row[:] = values
                continue
            for j, v in enumerate(values):
                if v is None:
                    row[j] = np.nan
                elif _is_number(v):
                    row[j] = v
                else:
                    raise self.error(f"{where}: {name}[{j}] is not a number: {v!r}")
        self.index += 1


def _message_capacity(fh: IO[bytes], size: int) -> int | None:
    """Number of messages in a complete file's statistics (to allocate once), else None."""
    fh.seek(size - len(_MCAP_MAGIC))
    if size < 2 * len(_MCAP_MAGIC) or fh.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
        fh.seek(0)
        return None  # no closing magic: cut file, no summary
    try:
        summary = SeekingReader(fh).get_summary()
    except Exception:  # a truncated or odd file has no usable summary: grow by blocks
        return None
    finally:
        fh.seek(0)
    if summary is None or summary.statistics is None:
        return None
    ids = [c.id for c in summary.channels.values() if c.topic == JOINT_STATES]
    counts = summary.statistics.channel_message_counts
    total = sum(counts.get(i, 0) for i in ids)
    # A message takes more than 16 bytes even compressed: a larger count is not to be trusted.
    return min(total, size // 16) or None


def _iter_records(fh: IO[bytes], size: int, path: Path) -> Iterator[Any]:
    """Records in file order; stops quietly at a cut (the reader can tell by the missing footer).

    A record that fails to parse is a cut when the reader reached the end of the file while
    reading it (the writer was killed mid-record); anywhere else it is corruption.
    """
    reader = StreamReader(fh, validate_crcs=True)
    records = reader.records
    while True:
        try:
            record = next(records)
        except StopIteration:
            return
        except Exception as exc:  # McapError, struct.error, zstd errors... from a record cut short
            if fh.tell() >= size:
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
    parser = _JointStateParser(p, _message_capacity(fh, size))
    meta: dict[str, str] | None = None
    attachments: dict[str, bytes] = {}
    events: list[dict[str, Any]] = []
    channels: dict[int, Channel] = {}
    footer = False
    for record in _iter_records(fh, size, p):
        if isinstance(record, Message):
            ch = channels.get(record.channel_id)
            if ch is None:
                continue
            if ch.topic == JOINT_STATES:
                parser.add(record)
            elif ch.topic == EVENTS and ch.message_encoding == "json":
                try:
                    ev = json.loads(record.data)
                except ValueError:
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


def _check_finite(arrays: dict[str, np.ndarray], joint_names: list[str], p: Path) -> None:
    for name in REQUIRED_VECTORS:
        finite = np.isfinite(arrays[name])
        if not finite.all():
            k, j = (int(x) for x in np.argwhere(~finite)[0])
            n_bad = int((~finite).any(axis=1).sum())
            raise DataError(
                f"{JOINT_STATES} message {k} (cycle {int(arrays['cycle'][k])}): "
                f"{name} of joint {joint_names[j]} is not finite (NaN, inf or null); "
                f"{n_bad} message(s) affected",
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
        for record in _iter_records(fh, size, p):
            if isinstance(record, Channel):
                channels[record.id] = record.topic
            elif isinstance(record, Message) and channels.get(record.channel_id) == topic:
                yield record.log_time, json.loads(record.data)
