"""The MCAP run log (contracts §4): writer checked with the mcap library's own reader, reader
checked on files other programs could write, on cut files and on killed writers."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import CompressionType, Writer

from drivegain.config import resource_path
from drivegain.errors import DataError
from drivegain.formats.columns import BLOCK_ROWS
from drivegain.formats.log import (
    EVENTS,
    JOINT_STATE_COLUMNS,
    JOINT_STATES,
    RAW,
    ROS2_JOINT_STATES,
    RunMetadata,
)
from drivegain.formats.logreader import read_run
from drivegain.formats.logwriter import LogWriter, write_run
from drivegain.identify.runs import excitation_start

HERE = Path(__file__).resolve().parent
NAMES = ["j1", "j2", "j3", "j4", "j5", "j6"]


def meta(**extra: str) -> RunMetadata:
    return RunMetadata(
        robot="Staubli TX-40",
        run="unloaded",
        payload="none",
        joint_names=NAMES,
        sync_period_s=0.004,
        started_at="2026-03-01T10:00:00.000Z",
        drivegain_version="0.1.0",
        extra=dict(extra),
    )


def signals(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "t": np.arange(n) * 0.004,
        "position": rng.normal(size=(n, 6)),
        "current_reference": rng.normal(size=(n, 6)) * 3,
        "current": rng.normal(size=(n, 6)),
        "setpoint": rng.normal(size=(n, 6)),
    }


def write_cycle(w: LogWriter, s: dict[str, np.ndarray], i: int, *, measured: bool = True) -> None:
    """Cycle ``i`` of the :func:`signals` ``s`` to ``w``, at log time ``i`` · 4 ms; without
    ``measured``, no current nor set-point (written as null)."""
    w.write_joint_state(
        cycle=i,
        t=s["t"][i],
        log_time_ns=i * 4_000_000,
        position=s["position"][i],
        current_reference=s["current_reference"][i],
        current=s["current"][i] if measured else None,
        setpoint=s["setpoint"][i] if measured else None,
    )


def one_line_naming(err: DataError, path: Path) -> str:
    text = str(err)
    assert "\n" not in text
    assert str(path) in text
    return text


# --- the writer, checked by the mcap library's reader ---------------------------------------


def test_writer_output_read_by_mcap_library(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    robot_bytes = resource_path("tx40.toml").read_bytes()
    blob = bytes(range(256)) * 3  # not text: attachments must be byte for byte
    s = signals(20_000)
    with LogWriter(
        out,
        meta(note="x"),
        [("robot.toml", "application/toml", robot_bytes), ("blob.bin", "x/bin", blob)],
    ) as w:
        assert w.part_path.exists() and not out.exists()
        for i in range(20_000):
            lt = 5_000_000_000 + i * 4_000_000
            w.write_joint_state(
                cycle=i,
                t=float(s["t"][i]),
                log_time_ns=lt,
                position=s["position"][i],
                current_reference=s["current_reference"][i],
                current=s["current"][i],
                setpoint=s["setpoint"][i],
            )
            w.write_raw(cycle=i, log_time_ns=lt, raw={"1": [i, 7, 0x1237]})
            if i == 10:
                w.write_event(
                    log_time_ns=lt,
                    level="info",
                    node=None,
                    code=None,
                    text="phase",
                    phase="excitation",
                )
    assert out.exists() and not (tmp_path / "run.mcap.part").exists()

    with out.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        # /joint_states, /drives/raw and the ROS 2 twin of /joint_states per cycle, one event,
        # and the rows again in blocks of BLOCK_ROWS on /joint_states/columns
        blocks = -(-20_000 // BLOCK_ROWS)
        assert summary.statistics.message_count == 3 * 20_000 + 1 + blocks
        assert summary.statistics.attachment_count == 2
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        assert len(summary.chunk_indexes) > 1  # about 4.5 MB of JSON in 1 MiB chunks
        # a chunk is closed by the message that fills it: at most one column block (55 kB) over
        assert max(c.uncompressed_size for c in summary.chunk_indexes) < (1 << 20) + 64 * 1024
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {JOINT_STATES, RAW, EVENTS, ROS2_JOINT_STATES, JOINT_STATE_COLUMNS}
        assert topics.pop(ROS2_JOINT_STATES).message_encoding == "cdr"
        columns = topics.pop(JOINT_STATE_COLUMNS)
        assert (columns.message_encoding, columns.schema_id) == ("msgpack", 0)
        for c in topics.values():
            assert c.message_encoding == "json"
            assert summary.schemas[c.schema_id].encoding == "jsonschema"
        schema = json.loads(summary.schemas[topics[JOINT_STATES].schema_id].data)
        assert set(schema["required"]) == {
            "cycle",
            "t",
            "position",
            "current_reference",
            "current",
            "setpoint",
        }
        (md,) = [m for m in reader.iter_metadata() if m.name == "drivegain.run"]
        assert md.metadata == {
            "format_version": "1",
            "robot": "Staubli TX-40",
            "run": "unloaded",
            "payload": "none",
            "joint_names": json.dumps(NAMES),
            "sync_period_s": "0.004",
            "started_at": "2026-03-01T10:00:00.000Z",
            "drivegain_version": "0.1.0",
            "note": "x",
        }
        att = {a.name: a for a in reader.iter_attachments()}
        assert att["robot.toml"].data == robot_bytes
        assert att["robot.toml"].media_type == "application/toml"
        assert att["blob.bin"].data == blob
        k = 0
        for _schema, _channel, message in reader.iter_messages(topics=[JOINT_STATES]):
            obj = json.loads(message.data)
            assert message.log_time == 5_000_000_000 + k * 4_000_000
            assert obj["cycle"] == k and obj["t"] == s["t"][k]
            for name in ("position", "current_reference", "current", "setpoint"):
                assert obj[name] == s[name][k].tolist()  # exact: JSON floats round-trip
            k += 1
        assert k == 20_000
        (ev,) = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=[EVENTS])]
        assert ev == {
            "level": "info",
            "node": None,
            "code": None,
            "text": "phase",
            "phase": "excitation",
        }

    log = read_run(out, n_joints=6)
    assert not log.truncated and log.messages_recovered == 20_000
    assert log.joint_names == NAMES and log.sync_period_s == 0.004 and log.rate_hz == 250.0
    np.testing.assert_array_equal(log.cycle, np.arange(20_000))
    for name in ("t", "position", "current_reference", "current", "setpoint"):
        np.testing.assert_array_equal(getattr(log, name), s[name])
    assert log.attachments == {"robot.toml": robot_bytes, "blob.bin": blob}
    assert [e["text"] for e in log.events] == ["phase"]
    assert log.events[0]["log_time_ns"] == 5_000_000_000 + 10 * 4_000_000
    assert log.missing_cycles() == 0
    assert excitation_start(log) == log.t[10]  # the phase event's cycle


def test_context_manager_finishes_after_a_fault(tmp_path: Path) -> None:
    out = tmp_path / "fault.mcap"
    s = signals(50)
    with pytest.raises(RuntimeError, match="drive fault"):
        with LogWriter(out, meta()) as w:
            for i in range(50):
                write_cycle(w, s, i, measured=False)
            raise RuntimeError("drive fault")
    with out.open("rb") as fh:  # complete: the library's seeking reader accepts it
        assert sum(1 for _ in make_reader(fh).iter_messages(topics=[JOINT_STATES])) == 50
    log = read_run(out)
    assert not log.truncated and log.messages_recovered == 50
    assert np.isnan(log.current).all() and np.isnan(log.setpoint).all()  # written as null


def test_non_finite_values_are_stored_as_null_and_rejected_where_needed(tmp_path: Path) -> None:
    s = signals(30)
    s["current"][3, 2] = np.inf
    out = write_run(
        tmp_path / "a.mcap", meta(), s["t"], s["position"], s["current_reference"], s["current"]
    )
    with out.open("rb") as fh:
        msgs = [
            json.loads(m.data) for _, _, m in make_reader(fh).iter_messages(topics=[JOINT_STATES])
        ]
    assert msgs[3]["current"][2] is None  # valid JSON, not the non-standard Infinity token
    log = read_run(out)  # a bad measured current does not stop identification
    assert (
        np.isnan(log.current[3, 2]) and np.isfinite(np.delete(log.current.ravel(), 3 * 6 + 2)).all()
    )

    s["position"][17, 4] = np.nan
    bad = write_run(tmp_path / "b.mcap", meta(), s["t"], s["position"], s["current_reference"])
    with pytest.raises(DataError) as exc:
        read_run(bad)
    text = one_line_naming(exc.value, bad)
    assert "message 17" in text and "position of joint j5" in text and "not finite" in text


# --- cut files and killed writers ------------------------------------------------------------


def test_close_unfinished_keeps_everything_flushed(tmp_path: Path) -> None:
    out = tmp_path / "crash.mcap"
    s = signals(300)
    w = LogWriter(out, meta(), [("robot.toml", "application/toml", b"abc")])
    for i in range(300):
        write_cycle(w, s, i)
        if i == 199:
            w.flush()
    w.close_unfinished()
    assert not out.exists()
    with pytest.raises(McapError):  # what design.md measured: the seeking reader refuses it
        with w.part_path.open("rb") as fh:
            list(make_reader(fh).iter_messages())
    log = read_run(w.part_path)
    assert log.truncated and log.messages_recovered == 200
    np.testing.assert_array_equal(log.position, s["position"][:200])
    assert log.attachments == {"robot.toml": b"abc"} and log.meta["run"] == "unloaded"


def _complete_chunks_messages(path: Path, cut: int) -> int:
    """Messages in the chunks that end before byte ``cut``, from the complete file's index."""
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    ends = [
        c.message_end_time
        for c in summary.chunk_indexes
        if c.chunk_start_offset + c.chunk_length <= cut
    ]
    if not ends:
        return 0
    return (max(ends) - 0) // 4_000_000 + 1  # log time = cycle * 4 ms


def _chunked_log(path: Path, n: int, chunk_size: int) -> tuple[Path, dict[str, np.ndarray]]:
    """A finished log of ``n`` cycles in small chunks (log time = cycle · 4 ms)."""
    s = signals(n)
    w = LogWriter(path, meta(), chunk_size=chunk_size)
    for i in range(n):
        write_cycle(w, s, i)
    return w.finish(), s


def test_any_cut_recovers_exactly_the_complete_chunks(tmp_path: Path) -> None:
    full, s = _chunked_log(tmp_path / "full.mcap", 2000, 16 * 1024)
    data = full.read_bytes()
    rng = np.random.default_rng(3)
    cuts = sorted({*rng.integers(8, len(data) - 1, size=40).tolist(), 9, 500, len(data) - 40})
    recovered_any = False
    for cut in cuts:
        part = tmp_path / f"cut{cut}.mcap.part"
        part.write_bytes(data[:cut])
        expected = _complete_chunks_messages(full, cut)
        if expected == 0:
            with pytest.raises(DataError) as exc:
                read_run(part)
            one_line_naming(exc.value, part)
            continue
        log = read_run(part)
        assert log.truncated, cut
        assert log.messages_recovered == expected, cut
        np.testing.assert_array_equal(log.position, s["position"][:expected])
        recovered_any = True
        # the library's non-seeking reader sees the same messages before it fails at the cut
        seen = 0
        with part.open("rb") as fh:
            try:
                for _ in NonSeekingReader(fh).iter_messages(
                    topics=[JOINT_STATES], log_time_order=False
                ):
                    seen += 1
            except Exception:
                pass
        assert seen == expected, cut
    assert recovered_any


def test_sigkill_mid_run_leaves_a_readable_part(tmp_path: Path) -> None:
    out = tmp_path / "killed.mcap"
    proc = subprocess.Popen(
        [sys.executable, str(HERE / "killed_writer.py"), str(out)],
        stdout=subprocess.PIPE,
        text=True,
    )
    flushed = 0
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            flushed = int(line.split()[1])
            if flushed >= 2000:
                break
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists()
    part = out.with_name(out.name + ".part")
    log = read_run(part)
    assert log.truncated
    assert log.messages_recovered >= flushed >= 2000  # nothing flushed is lost
    sys.path.insert(0, str(HERE))
    try:
        from killed_writer import expected
    finally:
        sys.path.remove(str(HERE))
    np.testing.assert_array_equal(log.cycle, np.arange(log.messages_recovered))
    want = expected(log.cycle)
    for name, values in want.items():
        np.testing.assert_array_equal(getattr(log, name), values)
    assert log.attachments == {"robot.toml": b"[robot]\n"}


# --- files from other programs ---------------------------------------------------------------


def _foreign_file(
    path: Path,
    messages: list[tuple[int, dict]],
    *,
    metadata: dict[str, str] | None,
    chunked: bool = True,
    topic: str = JOINT_STATES,
    encoding: str = "json",
    metadata_last: bool = False,
    raw_messages: list[tuple[int, bytes]] | None = None,
) -> Path:
    """A log written directly with the mcap library, as another program would."""
    with path.open("wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE, use_chunking=chunked, chunk_size=4096)
        w.start(profile="", library="someone else 2.0")
        if metadata is not None and not metadata_last:
            w.add_metadata("drivegain.run", metadata)
        w.add_metadata("other", {"a": "b"})
        tf = w.register_channel("/tf", "json", 0)
        sid = w.register_schema("JS", "jsonschema", b"{}")
        ch = w.register_channel(topic, encoding, sid)
        w.add_message(tf, 0, b"{}", 0)
        for lt, obj in messages:
            w.add_message(ch, lt, json.dumps(obj).encode(), lt)
        for lt, data in raw_messages or []:
            w.add_message(ch, lt, data, lt)
        if metadata is not None and metadata_last:
            w.add_metadata("drivegain.run", metadata)
        w.finish()
    return path


def foreign_meta(**changes: str) -> dict[str, str]:
    m = {
        "format_version": "1",
        "robot": "other arm",
        "run": "loaded",
        "payload": "p1",
        "joint_names": json.dumps(["a", "b", "c"]),
        "sync_period_s": "0.001",
        "started_at": "2025-12-01T00:00:00Z",
        "drivegain_version": "other-tool 3",
        "vendor_key": "kept",
    }
    m.update(changes)
    return {k: v for k, v in m.items() if v != "<drop>"}


def foreign_messages(n: int, **override: object) -> list[tuple[int, dict]]:
    out = []
    for i in range(n):
        obj: dict = {
            "cycle": i + 100,
            "t": i * 0.001,
            "position": [i, 2 * i, -i],  # integers are numbers too
            "current_reference": [0.5, 0.25 * i, 1e-3],
        }
        obj.update({k: v(i) if callable(v) else v for k, v in override.items()})
        out.append((7_000_000_000 + i * 1_000_000, obj))
    return out


def test_foreign_file_unchunked_out_of_order_metadata_last(tmp_path: Path) -> None:
    msgs = foreign_messages(50)
    shuffled = [msgs[i] for i in np.random.default_rng(1).permutation(50)]
    p = _foreign_file(
        tmp_path / "f.mcap", shuffled, metadata=foreign_meta(), chunked=False, metadata_last=True
    )
    log = read_run(p, n_joints=3)
    assert not log.truncated and log.messages_recovered == 50
    np.testing.assert_array_equal(log.cycle, np.arange(50) + 100)  # put in log-time order
    np.testing.assert_array_equal(log.position[:, 1], 2.0 * np.arange(50))
    assert np.isnan(log.current).all() and np.isnan(log.setpoint).all()  # optional fields
    assert log.meta["vendor_key"] == "kept" and log.joint_names == ["a", "b", "c"]
    assert log.events == [] and log.attachments == {}


def test_foreign_file_chunked_with_other_channels(tmp_path: Path) -> None:
    p = _foreign_file(tmp_path / "g.mcap", foreign_messages(400), metadata=foreign_meta())
    log = read_run(p)
    assert log.messages_recovered == 400 and log.sync_period_s == 0.001


# --- one-line errors naming the file ---------------------------------------------------------


def _expect_error(path: Path, *fragments: str, n_joints: int | None = None) -> None:
    with pytest.raises(DataError) as exc:
        read_run(path, n_joints=n_joints)
    text = one_line_naming(exc.value, path)
    for f in fragments:
        assert f in text, text


def test_not_mcap_empty_missing(tmp_path: Path) -> None:
    text = tmp_path / "notes.mcap"
    text.write_text("joint,position\n1,2\n")
    _expect_error(text, "not an MCAP file")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    _expect_error(empty, "empty file")
    _expect_error(tmp_path / "absent.mcap", "file not found")


@pytest.mark.parametrize(
    ("case", "fragments"),
    [
        ("no_channel", ["missing channel /joint_states", "/tf"]),
        ("no_metadata", ["no metadata record 'drivegain.run'"]),
        ("missing_keys", ["lacks keys: sync_period_s, started_at"]),
        ("bad_names", ["'joint_names' must be a JSON list"]),
        ("bad_period", ["'sync_period_s' must be a positive number"]),
        ("version", ["unsupported format_version '2'"]),
        ("no_messages", ["no messages on /joint_states"]),
        ("short_vector", ["message 3 (cycle 103)", "'current_reference' has 2 values, expected 3"]),
        ("names_vs_messages", ["messages carry 3 joints, metadata joint_names has 4"]),
        ("time_backwards", ["'t' not strictly increasing at message 5", "cycle 105"]),
        ("cycle_repeats", ["'cycle' not strictly increasing at message 8"]),
        ("nan_token", ["message 2 (cycle 102)", "position of joint b is not finite"]),
        ("inf_current", ["current_reference of joint c is not finite"]),
        ("bool_value", ["position[0] is not a number: True"]),
        ("missing_field", ["field 'current_reference' missing"]),
        ("not_json", ["message 0 is not valid JSON"]),
        ("cdr", ["message encoding 'cdr', expected 'json'"]),
    ],
)
def test_malformed_logs(tmp_path: Path, case: str, fragments: list[str]) -> None:
    p = tmp_path / f"{case}.mcap"
    m, msgs = foreign_meta(), foreign_messages(10)
    kw: dict = {}
    if case == "no_channel":
        kw["topic"] = "/something_else"
    elif case == "no_metadata":
        m = None  # type: ignore[assignment]
    elif case == "missing_keys":
        m = foreign_meta(sync_period_s="<drop>", started_at="<drop>")
    elif case == "bad_names":
        m = foreign_meta(joint_names="a,b,c")
    elif case == "bad_period":
        m = foreign_meta(sync_period_s="-1")
    elif case == "version":
        m = foreign_meta(format_version="2")
    elif case == "no_messages":
        msgs = []
    elif case == "short_vector":
        msgs[3][1]["current_reference"] = [1.0, 2.0]
    elif case == "names_vs_messages":
        m = foreign_meta(joint_names=json.dumps(["a", "b", "c", "d"]))
    elif case == "time_backwards":
        msgs[5][1]["t"] = msgs[4][1]["t"]
    elif case == "cycle_repeats":
        msgs[8][1]["cycle"] = msgs[7][1]["cycle"]
    elif case == "nan_token":
        msgs[2][1]["position"][1] = float("nan")  # json.dumps writes the NaN token
    elif case == "inf_current":
        msgs[6][1]["current_reference"][2] = float("inf")
    elif case == "bool_value":
        msgs[0][1]["position"][0] = True
    elif case == "missing_field":
        del msgs[4][1]["current_reference"]
    elif case == "not_json":
        kw["raw_messages"] = [(1, b"{not json")]
        msgs = []
    elif case == "cdr":
        kw["encoding"] = "cdr"
    _foreign_file(p, msgs, metadata=m, **kw)
    _expect_error(p, *fragments)


def test_wrong_joint_count_for_the_robot(tmp_path: Path) -> None:
    s = signals(40)
    p = write_run(tmp_path / "r.mcap", meta(), s["t"], s["position"], s["current_reference"])
    _expect_error(p, "log has 6 joints (j1, j2, j3, j4, j5, j6), the robot has 7", n_joints=7)


def test_write_run_leaves_nothing_on_error(tmp_path: Path) -> None:
    s = signals(40)
    with pytest.raises(DataError, match=r"position.*has 3 values"):
        write_run(tmp_path / "x.mcap", meta(), s["t"], s["position"][:, :3], s["current_reference"])
    assert list(tmp_path.iterdir()) == []


def test_corruption_inside_the_file_is_not_taken_for_a_cut(tmp_path: Path) -> None:
    s = signals(3000)
    p = write_run(tmp_path / "c.mcap", meta(), s["t"], s["position"], s["current_reference"])
    data = bytearray(p.read_bytes())
    with p.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    chunk = summary.chunk_indexes[0]
    mid = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[mid : mid + 16] = bytes(16)
    p.write_bytes(bytes(data))
    _expect_error(p, "corrupt MCAP data at byte")


def test_write_run_helper_with_events_and_gaps(tmp_path: Path) -> None:
    s = signals(100)
    keep = np.delete(np.arange(100), [10, 11, 50])  # three lost cycles
    events = [
        {
            "log_time_ns": int(0.3e9),
            "level": "warning",
            "node": 3,
            "code": 0x8130,
            "text": "heartbeat",
        },
        {
            "log_time_ns": 0,
            "level": "info",
            "node": None,
            "code": None,
            "text": "start",
            "phase": "approach",
        },
    ]
    p = write_run(
        tmp_path / "w.mcap",
        meta(),
        s["t"][keep],
        s["position"][keep],
        s["current_reference"][keep],
        cycle=keep,
        events=events,
    )
    with p.open("rb") as fh:
        ev = [
            (m.log_time, json.loads(m.data)["text"])
            for _, _, m in make_reader(fh).iter_messages(topics=[EVENTS])
        ]
    assert ev == [(0, "start"), (300_000_000, "heartbeat")]
    log = read_run(p)
    assert log.missing_cycles() == 3 and log.messages_recovered == 97
    assert log.events[0]["phase"] == "approach" and log.events[1]["code"] == 0x8130
    assert excitation_start(log) is None  # no excitation phase in this log


# --- corruption is never read as a shorter file -------------------------------------------


def test_a_corrupt_record_length_is_not_a_cut(tmp_path: Path) -> None:
    """A record length pointing past the end of a finished file sends the reader to the end: it
    used to report a cut file and drop every later cycle."""
    p, _ = _chunked_log(tmp_path / "base.mcap", 300, 4 * 1024)
    data = p.read_bytes()
    with p.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 3
    for length in (2**31, len(data)):
        bad = bytearray(data)
        start = summary.chunk_indexes[0].chunk_start_offset
        bad[start + 1 : start + 9] = length.to_bytes(8, "little")  # after the opcode byte
        q = tmp_path / f"len{length}.mcap"
        q.write_bytes(bytes(bad))
        _expect_error(q, "corrupt MCAP data at byte")


def test_mutated_logs_are_read_whole_or_refused(tmp_path: Path) -> None:
    """Seeded fuzzing: a complete-size file with a flipped byte, a zeroed word or a random
    64-bit value is either read in full with the original data or refused with one line naming
    the file; never reported as cut, never shorter, never a crash."""
    p, s = _chunked_log(tmp_path / "base.mcap", 300, 4 * 1024)
    data = p.read_bytes()
    rng = np.random.default_rng(2026)
    outcomes = {"read": 0, "refused": 0}
    q = tmp_path / "mutated.mcap"
    for k in range(300):
        bad = bytearray(data)
        i = int(rng.integers(8, len(data) - 16))
        if k % 3 == 0:
            bad[i] ^= int(rng.integers(1, 256))
        elif k % 3 == 1:
            bad[i : i + 4] = bytes(4)
        else:
            bad[i : i + 8] = int(rng.integers(0, 2**63)).to_bytes(8, "little")
        q.write_bytes(bytes(bad))
        try:
            log = read_run(q)
        except DataError as exc:
            one_line_naming(exc, q)
            outcomes["refused"] += 1
            continue
        assert not log.truncated, (k, i)
        assert log.messages_recovered == len(s["t"]), (k, i)
        np.testing.assert_array_equal(log.position, s["position"], err_msg=f"mutation {k}")
        outcomes["read"] += 1
    assert outcomes["refused"] > 100 and outcomes["read"] > 0, outcomes


def _message(**fields: object) -> str:
    vec = [0.0] * 6
    obj: dict[str, object] = {"cycle": 0, "t": 0.0, "position": vec, "current_reference": vec}
    obj.update(fields)
    return json.dumps(obj)


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        (_message(cycle=2**70), "field 'cycle' is out of range"),
        (_message(t=10**400), "field 't' is out of range"),
        (_message(position=[10**400, 0, 0, 0, 0, 0]), "position[0] is out of range"),
        ('{"cycle": 0, "deep": ' + "[" * 30_000 + "]" * 30_000 + "}", "is not valid JSON"),
    ],
    ids=["cycle-2**70", "t-10**400", "position-10**400", "nested-json"],
)
def test_numbers_out_of_range_and_deep_json_are_data_errors(
    tmp_path: Path, text: str, fragment: str
) -> None:
    out = tmp_path / "odd.mcap"
    with out.open("wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start()
        w.add_metadata("drivegain.run", meta().to_record())
        sid = w.register_schema("js", "jsonschema", b"{}")
        cid = w.register_channel(JOINT_STATES, "json", sid)
        w.add_message(cid, log_time=0, data=text.encode(), publish_time=0)
        w.finish()
    _expect_error(out, fragment)


def test_an_implausible_value_is_named_before_any_filtering(tmp_path: Path) -> None:
    s = signals(50)
    s["position"][7, 2] = 1e300
    p = write_run(tmp_path / "big.mcap", meta(), s["t"], s["position"], s["current_reference"])
    _expect_error(p, "message 7 (cycle 7)", "position of joint j3 is 1e+300", "1 message(s)")
    s = signals(50)
    s["current"][3, 0] = -1e12  # optional channels are checked for magnitude too
    p = write_run(
        tmp_path / "cur.mcap", meta(), s["t"], s["position"], s["current_reference"], s["current"]
    )
    _expect_error(p, "message 3 (cycle 3)", "current of joint j1 is -1e+12")
