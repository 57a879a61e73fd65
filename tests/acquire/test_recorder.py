"""The recorder thread: every cycle reaches the MCAP file, bounded memory, flushing, failures."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from drivegain.acquire.recorder import (
    CycleRecord,
    EventRecord,
    Recorder,
    RecorderError,
    RecorderOverrun,
)
from drivegain.formats.log import EventLevel, RunMetadata
from drivegain.formats.logreader import read_run
from drivegain.formats.logwriter import LogWriter

N = 6
PERIOD = 0.004


def _meta() -> RunMetadata:
    return RunMetadata(
        robot="test robot",
        run="unloaded",
        payload="none",
        joint_names=[f"j{i + 1}" for i in range(N)],
        sync_period_s=PERIOD,
        started_at="2025-01-01T00:00:00.000+00:00",
        drivegain_version="0",
    )


def _record(k: int) -> CycleRecord:
    base = np.arange(N, dtype=float)
    return CycleRecord(
        cycle=k,
        t=k * PERIOD,
        log_time_ns=1_000_000_000 + k * 4_000_000,
        position=np.sin(0.01 * k + base),
        current_reference=np.cos(0.01 * k + base),
        current=0.5 * np.cos(0.01 * k + base),
        setpoint=np.sin(0.01 * k + base) + 1e-3,
        raw={str(i + 1): [k, i, 0x1237] for i in range(N)},
    )


def test_every_cycle_and_event_reaches_the_file(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    rec = Recorder(LogWriter(out, _meta()), capacity=64, flush_interval_s=0.05)
    rec.start()
    rec.put_event(EventRecord(log_time_ns=999_000_000, level="info", text="run started"))
    for k in range(3000):
        rec.put_cycle(_record(k), block=True)
    rec.put_event(
        EventRecord(
            log_time_ns=1_000_000_000 + 3000 * 4_000_000,
            level=EventLevel.ERROR,
            text="boom",
            node=3,
            code=0x8611,
            fields={"cycle": 2999},
        )
    )
    path = rec.finish()
    assert path == out and out.exists() and not (tmp_path / "run.mcap.part").exists()
    assert rec.high_water <= 64

    # the mcap library's own reader: every cycle once, in order, no gap
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        cycles, raw_cycles, events = [], [], []
        for _schema, channel, message in reader.iter_messages():
            if channel.message_encoding != "json":
                continue  # the ROS 2 twin of /joint_states (CDR): tests/identify_data
            obj = json.loads(message.data)
            if channel.topic == "/joint_states":
                cycles.append(obj["cycle"])
            elif channel.topic == "/drives/raw":
                raw_cycles.append(obj["cycle"])
            elif channel.topic == "/events":
                events.append(obj)
    assert cycles == list(range(3000))
    assert raw_cycles == list(range(3000))
    assert [e["text"] for e in events] == ["run started", "boom"]
    assert events[-1]["node"] == 3 and events[-1]["code"] == 0x8611

    run = read_run(out)
    assert not run.truncated
    np.testing.assert_array_equal(run.cycle, np.arange(3000))
    expected = np.array([_record(k).position for k in range(3000)])
    np.testing.assert_allclose(run.position, expected, rtol=0, atol=1e-15)


class _SlowSink:
    """A sink that writes nothing and records which thread called it (and can be held)."""

    def __init__(self) -> None:
        self.threads: set[str] = set()
        self.gate = threading.Event()
        self.gate.set()
        self.cycles = 0
        self.flushes = 0
        self.fail_at: int | None = None

    def write_joint_state(self, **kw: Any) -> None:
        self.gate.wait()
        self.threads.add(threading.current_thread().name)
        if self.fail_at is not None and kw["cycle"] >= self.fail_at:
            raise OSError(28, "No space left on device")
        self.cycles += 1

    def write_raw(self, **kw: Any) -> None:
        self.threads.add(threading.current_thread().name)

    def write_event(self, **kw: Any) -> None:
        self.threads.add(threading.current_thread().name)

    def flush(self) -> None:
        self.flushes += 1

    def finish(self) -> Path:
        return Path("finished")

    def close_unfinished(self) -> None:
        pass


def test_writes_only_on_the_recorder_thread_and_memory_is_bounded() -> None:
    sink = _SlowSink()
    rec = Recorder(sink, capacity=16, flush_interval_s=0.01)
    rec.start()
    sink.gate.clear()  # the "disk" stalls: a blocking producer must wait, not grow the queue
    done = threading.Event()

    def produce() -> None:
        for k in range(200):
            rec.put_cycle(_record(k), block=True)
        done.set()

    th = threading.Thread(target=produce)
    th.start()
    time.sleep(0.2)
    assert not done.is_set()
    assert rec.high_water <= 16
    sink.gate.set()
    th.join(5)
    assert done.is_set()
    rec.finish()
    assert sink.cycles == 200
    assert sink.threads == {"drivegain-recorder"}
    assert sink.flushes >= 1


def test_full_queue_in_realtime_is_an_overrun_not_a_silent_drop() -> None:
    sink = _SlowSink()
    sink.gate.clear()
    rec = Recorder(sink, capacity=8)
    rec.start()
    with pytest.raises(RecorderOverrun, match="cannot keep up"):
        for k in range(100):
            rec.put_cycle(_record(k), block=False)
    sink.gate.set()
    rec.finish()
    # everything accepted was written: the overrun cycle is the first one missing
    assert sink.cycles == rec.written_cycles


def test_writer_failure_stops_the_producer_and_keeps_the_part() -> None:
    sink = _SlowSink()
    sink.fail_at = 10
    rec = Recorder(sink, capacity=1000)
    rec.start()
    with pytest.raises(RecorderError, match="No space left"):
        for k in range(10_000):
            rec.put_cycle(_record(k), block=True)
            time.sleep(0.0001)
    with pytest.raises(RecorderError, match="No space left"):
        rec.finish()


def test_periodic_flush_makes_the_part_readable_while_running(tmp_path: Path) -> None:
    """What a SIGKILL would leave: the .part holds every cycle queued before the last flush."""
    out = tmp_path / "run.mcap"
    writer = LogWriter(out, _meta())
    rec = Recorder(writer, capacity=4096, flush_interval_s=0.05)
    rec.start()
    for k in range(500):
        rec.put_cycle(_record(k), block=True)
    deadline = time.monotonic() + 5
    while rec.written_cycles < 500 and time.monotonic() < deadline:
        time.sleep(0.01)
    flushes = rec.flushes
    while rec.flushes < flushes + 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    part = read_run(tmp_path / "run.mcap.part")  # the writer is still open
    assert part.truncated
    np.testing.assert_array_equal(part.cycle, np.arange(500))
    rec.abandon()
    assert (tmp_path / "run.mcap.part").exists() and not out.exists()


def test_an_unfinished_log_without_cycles_is_discarded_one_with_cycles_kept(
    tmp_path: Path,
) -> None:
    """A full disk before a run left a 0-byte .part that blocked the retry: a .part that holds
    no recorded cycle is removed after a failed run, one that holds cycles never is."""
    from drivegain.acquire.recorder import discard_unrecorded, holds_cycles, part_path

    empty = tmp_path / "empty.mcap"
    part_path(empty).write_bytes(b"")
    header_only = tmp_path / "header.mcap"
    LogWriter(header_only, _meta(), [("t.json", "application/json", b"{}")]).close_unfinished()
    recorded = tmp_path / "recorded.mcap"
    w = LogWriter(recorded, _meta())
    for k in range(5):
        r = _record(k)
        w.write_joint_state(
            cycle=r.cycle,
            t=r.t,
            log_time_ns=r.log_time_ns,
            position=r.position,
            current_reference=r.current_reference,
            current=r.current,
            setpoint=r.setpoint,
        )
    w.flush()
    w.close_unfinished()
    assert not holds_cycles(part_path(empty)) and not holds_cycles(part_path(header_only))
    assert holds_cycles(part_path(recorded))
    assert discard_unrecorded(empty) and not part_path(empty).exists()
    assert discard_unrecorded(header_only) and not part_path(header_only).exists()
    assert not discard_unrecorded(recorded) and part_path(recorded).exists()
    assert not discard_unrecorded(tmp_path / "never.mcap")  # nothing there: nothing to do


def test_a_log_that_cannot_be_started_is_one_line_and_leaves_nothing(tmp_path: Path) -> None:
    """What the session's log creation raises on a full disk (ENOSPC after the .part was
    created) becomes one line naming the file, and the empty .part goes."""
    import errno
    from types import SimpleNamespace

    from drivegain.acquire.foreground import run_session
    from drivegain.acquire.recorder import discard_unrecorded, part_path
    from drivegain.acquire.session import RunState
    from drivegain.errors import InputError

    out = tmp_path / "run.mcap"

    class FullDisk:
        state = RunState.PLANNED
        prepared = SimpleNamespace(request=SimpleNamespace(out=out))

        def run(self) -> None:
            part_path(out).write_bytes(b"")
            raise OSError(errno.ENOSPC, "No space left on device")

    outcome = run_session(FullDisk())
    err = outcome["error"]
    assert isinstance(err, InputError)
    assert str(err).startswith(f"{part_path(out)}: cannot write the log (No space left")
    assert "\n" not in str(err)
    assert discard_unrecorded(out) and not part_path(out).exists()
