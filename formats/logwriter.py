"""Writing the acquisition log (contracts.md §4).

:class:`LogWriter` streams one run to ``NAME.mcap.part`` (zstd chunks of 1 MiB) and renames it to
``NAME.mcap`` when :meth:`LogWriter.finish` is called. The metadata record and the attachments are
written and flushed first, so even a writer killed in its first second leaves a file that says
what it was recording. :func:`write_run` writes a whole run from arrays.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import msgspec
import numpy as np
from mcap.writer import CompressionType, Writer

from drivegain import __version__
from drivegain.errors import DataError, UsageError
from drivegain.fileio import fsync_dir
from drivegain.formats.columns import ColumnBuffer
from drivegain.formats.log import (
    DEFAULT_CHUNK_SIZE,
    EVENT_SCHEMA,
    EVENTS,
    JOINT_STATE_COLUMNS,
    JOINT_STATES,
    METADATA_NAME,
    RAW,
    ROS2_JOINT_STATES,
    RunMetadata,
    joint_state_schema,
    raw_schema,
)
from drivegain.formats.ros2 import (
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    SCHEMA_NAME,
    SCHEMA_TEXT,
    JointStateEncoder,
)


def _json_bytes(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False, default=str).encode()


#: The messages of every cycle (``/joint_states``, ``/drives/raw``): msgspec encodes them about
#: 15 times faster than ``json.dumps`` (the recorder thread shares the interpreter with the
#: cycle loop). JSON has no NaN: it writes a non-finite float as null, which readers reject
#: where the value is needed. Floats are the shortest text that reads back to the same value.
_cycle_json = msgspec.json.Encoder().encode


def _vector(value: Any, n: int, name: str) -> list[float]:
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.size != n:
        raise DataError(f"has {arr.size} values, the log has {n} joints", key=name)
    out: list[float] = arr.tolist()
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
    effort_gains
        Drive gains, N·m/A per joint, for the efforts of the ROS 2 JointState channel (current
        reference × gain); ``None`` (the default) leaves them empty, as the channel's metadata
        then says.

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
        effort_gains: Sequence[float] | None = None,
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
            "drivegain.DrivesRaw", "jsonschema", _json_bytes(raw_schema(meta.joint_names))
        )
        es = self._writer.register_schema(
            "drivegain.Event", "jsonschema", _json_bytes(EVENT_SCHEMA)
        )
        self._joint_states = self._writer.register_channel(JOINT_STATES, "json", js)
        self._raw = self._writer.register_channel(RAW, "json", rs)
        self._events = self._writer.register_channel(EVENTS, "json", es)
        self._ros2 = JointStateEncoder(meta.joint_names, effort_gains)
        ros2_schema = self._writer.register_schema(
            SCHEMA_NAME, SCHEMA_ENCODING, SCHEMA_TEXT.encode()
        )
        self._ros2_joint_states = self._writer.register_channel(
            ROS2_JOINT_STATES,
            MESSAGE_ENCODING,
            ros2_schema,
            metadata={
                "position": "rad, joint side, as /joint_states",
                "velocity": "empty: not measured",
                "effort": "N·m: current_reference × the drive gains given to the writer"
                if effort_gains is not None
                else "empty: the log does not know the drive gains",
            },
        )
        # schema id 0: MessagePack maps describe themselves (formats/columns.py has the layout)
        self._columns = self._writer.register_channel(
            JOINT_STATE_COLUMNS,
            "msgpack",
            0,
            metadata={"twin_of": JOINT_STATES, "layout": "drivegain.formats.columns version 1"},
        )
        self._column_buffer = ColumnBuffer(self._n)
        self._names = list(meta.joint_names)
        self._sequence = {
            self._joint_states: 0,
            self._columns: 0,
            self._raw: 0,
            self._events: 0,
            self._ros2_joint_states: 0,
        }
        self.messages = 0
        self.flush()

    def _add(self, channel: int, log_time_ns: int, data: bytes) -> None:
        if self._done:
            raise UsageError(f"{self.part_path}: log already finished or closed")
        if log_time_ns < 0:
            raise DataError(f"must be >= 0 ns, got {log_time_ns}", key="log_time_ns")
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
        cycle, t = int(cycle), float(t)
        msg = {
            "cycle": cycle,
            "t": t,
            "position": _vector(position, n, "position"),
            "current_reference": _vector(current_reference, n, "current_reference"),
            "current": nulls if current is None else _vector(current, n, "current"),
            "setpoint": nulls if setpoint is None else _vector(setpoint, n, "setpoint"),
            "name": self._names,
        }
        self._add(self._joint_states, log_time_ns, _cycle_json(msg))
        buffer = self._column_buffer
        buffer.append(
            cycle,
            t,
            log_time_ns,
            {
                "position": position,
                "current_reference": current_reference,
                "current": current,
                "setpoint": setpoint,
            },
        )
        if buffer.full:
            self._write_columns()
        # NaN stays NaN in CDR (float64), where JSON has null
        self._add(
            self._ros2_joint_states,
            log_time_ns,
            self._ros2.encode(
                log_time_ns,
                np.asarray(position, dtype=float),
                np.asarray(current_reference, dtype=float),
            ),
        )

    def _write_columns(self) -> None:
        """Write the rows buffered since the last block to ``/joint_states/columns``."""
        buffer = self._column_buffer
        if buffer.used:
            self._add(self._columns, buffer.last_log_time_ns, buffer.take())

    def write_raw(self, *, cycle: int, log_time_ns: int, raw: Mapping[str, Any]) -> None:
        """Append the raw drive values of one cycle to ``/drives/raw`` (JSON-serialisable)."""
        self._add(self._raw, log_time_ns, _cycle_json({"cycle": int(cycle), "raw": dict(raw)}))

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
            raise UsageError(f"event fields reuse reserved keys {sorted(clash)}")
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
        self._write_columns()
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
                raise UsageError(f"{self.part_path}: log was closed unfinished")
            return self.path
        self._write_columns()
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        self._done = True
        os.replace(self.part_path, self.path)
        fsync_dir(self.path.parent)
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
    effort_gains: Sequence[float] | None = None,
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
    effort_gains
        Drive gains, N·m/A, for the efforts of the ROS 2 channel (see :class:`LogWriter`).

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
            raise DataError(f"has {arr.shape[0]} samples, t has {n_samples}", key=name)
    cyc = np.arange(n_samples) if cycle is None else np.asarray(cycle, dtype=np.int64)
    lt = np.rint(t * 1e9).astype(np.int64) if log_time_ns is None else np.asarray(log_time_ns)
    writer = LogWriter(path, meta, attachments, effort_gains=effort_gains)
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
