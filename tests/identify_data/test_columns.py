"""The ``/joint_states/columns`` side channel (formats/columns.py): what the writer stores, that
the reader's result with it is the JSON messages' to the bit, and that blocks which disagree
with the JSON messages are not used."""

from __future__ import annotations

import functools
import logging
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import IndexType, Writer

import drivegain.formats.logreader as logreader
import drivegain.formats.logwriter as logwriter
from drivegain.errors import DataError
from drivegain.formats.columns import BLOCK_ROWS, SPOT_EVERY, ColumnBuffer
from drivegain.formats.log import JOINT_STATE_COLUMNS
from drivegain.formats.logreader import RunLog, read_run
from drivegain.formats.logwriter import LogWriter, write_run

from .test_logformat import meta, signals, write_cycle

FIELDS = ("cycle", "t", "log_time_ns", "position", "current_reference", "current", "setpoint")


def read_json(path: Path) -> RunLog:
    """The run as read from its JSON messages alone (the side channel ignored)."""
    with path.open("rb") as fh:
        return logreader._read_stream(fh, os.fstat(fh.fileno()).st_size, path, None, columns=False)


def assert_same(a: RunLog, b: RunLog) -> None:
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), name
    assert a.messages_recovered == b.messages_recovered and a.truncated == b.truncated


def write_mixed(out: Path, n: int = 700, flush_at: int = 300) -> dict[str, np.ndarray]:
    """``n`` cycles: every 7th without current nor set-point, an infinite set-point at cycle 5,
    a flush after ``flush_at`` cycles."""
    s = signals(n, seed=3)
    s["setpoint"][5, 2] = np.inf
    with LogWriter(out, meta()) as w:
        for i in range(n):
            write_cycle(w, s, i, measured=i % 7 != 0)
            if i in (10, 400):
                w.write_event(
                    log_time_ns=i * 4_000_000, level="info", node=None, code=i, text="phase"
                )
            if i + 1 == flush_at:
                w.flush()
    return s


def block_rows(path: Path) -> list[int]:
    """Rows of each ``/joint_states/columns`` block, in file order (mcap library's reader)."""
    import msgspec

    with path.open("rb") as fh:
        return [
            msgspec.msgpack.decode(m.data)["rows"]
            for _, _, m in make_reader(fh).iter_messages(topics=[JOINT_STATE_COLUMNS])
        ]


@pytest.mark.parametrize(
    "index",
    [IndexType.ALL, IndexType.CHUNK],
    ids=["chunks read through their message indexes", "chunks cut into records"],
)
def test_blocks_are_read_in_place_of_the_json_messages_and_give_the_same_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, index: IndexType
) -> None:
    monkeypatch.setattr(logwriter, "Writer", functools.partial(Writer, index_types=index))
    out = tmp_path / "run.mcap"
    s = write_mixed(out)
    with out.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    assert all(
        bool(c.message_index_offsets) == (index == IndexType.ALL) for c in summary.chunk_indexes
    )
    # blocks close when full, at a flush and at the end
    assert block_rows(out) == [BLOCK_ROWS, 300 - BLOCK_ROWS, BLOCK_ROWS, 400 - BLOCK_ROWS]

    slow = read_json(out)
    decoded: list[int] = []
    real = logreader.decode_block

    def counting(data: bytes) -> dict[str, np.ndarray]:
        block = real(data)
        decoded.append(block["cycle"].size)
        return block

    monkeypatch.setattr(logreader, "decode_block", counting)
    monkeypatch.setattr(
        logreader.JointStateParser, "_fast", lambda *a: pytest.fail("a JSON batch was decoded")
    )
    fast = read_run(out)
    assert decoded == block_rows(out)
    assert_same(fast, slow)
    assert [e["code"] for e in fast.events] == [10, 400] and fast.events == slow.events
    # and both are what was written (null -> NaN, inf -> NaN)
    assert np.array_equal(fast.position, s["position"])
    assert np.isnan(fast.current[::7]).all() and np.isnan(fast.setpoint[5, 2])
    assert np.array_equal(fast.current[1:7], s["current"][1:7])


def test_a_non_finite_position_gives_the_same_error_either_way(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    s = signals(50)
    s["position"][17, 3] = np.nan
    write_run(out, meta(), s["t"], s["position"], s["current_reference"])
    with pytest.raises(DataError) as fast:
        read_run(out)
    with pytest.raises(DataError) as slow:
        read_json(out)
    assert str(fast.value) == str(slow.value)


class _Tampered(ColumnBuffer):
    """A buffer whose first block is altered as ``how`` says (a writer gone wrong)."""

    how = ""
    blocks = 0

    def take(self) -> bytes:
        first = _Tampered.blocks == 0
        _Tampered.blocks += 1
        if first and self.how == "value in a row checked whole":
            self._vectors["current_reference"][SPOT_EVERY, 4] += 1e-12
        elif first and self.how == "log time of a row not checked whole":
            self._log_time[SPOT_EVERY + 1] += 1
        elif first and self.how == "a row missing":
            self.used -= 1
        elif first and self.how == "garbage":
            self.used = 0
            return b"\xc1 not a block"
        return super().take()


@pytest.mark.parametrize(
    ("where", "value", "said"),
    [
        (6 + 8, struct.pack("<Q", 3), "chunk offset 3"),  # the first entry's offset
        (2, struct.pack("<I", 17), "holds 17 bytes"),  # the entries' length
    ],
    ids=["an entry's offset", "the entries' length"],
)
def test_a_damaged_message_index_leaves_the_json_messages_to_read(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, where: int, value: bytes, said: str
) -> None:
    out = tmp_path / "run.mcap"
    s = write_mixed(out, n=2 * BLOCK_ROWS, flush_at=0)
    data = bytearray(out.read_bytes())
    at = len(b"\x89MCAP0\r\n")
    while data[at] != 0x07:  # the first message index record
        at += 9 + struct.unpack_from("<Q", data, at + 1)[0]
    data[at + 9 + where : at + 9 + where + len(value)] = value
    out.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger=logreader.__name__):
        got = read_run(out)
    assert_same(got, read_json(out))
    assert np.array_equal(got.position, s["position"])
    (record,) = caplog.records
    assert said in record.getMessage()


@pytest.mark.parametrize(
    "how",
    [
        "value in a row checked whole",
        "log time of a row not checked whole",
        "a row missing",
        "garbage",
    ],
)
def test_blocks_that_disagree_with_the_json_messages_are_not_used(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, how: str
) -> None:
    monkeypatch.setattr(_Tampered, "how", how)
    monkeypatch.setattr(_Tampered, "blocks", 0)
    monkeypatch.setattr(logwriter, "ColumnBuffer", _Tampered)
    out = tmp_path / "run.mcap"
    s = write_mixed(out, n=2 * BLOCK_ROWS, flush_at=0)
    with caplog.at_level(logging.WARNING, logger=logreader.__name__):
        got = read_run(out)
    assert_same(got, read_json(out))
    assert np.array_equal(got.current_reference, s["current_reference"])
    (record,) = caplog.records
    assert str(out) in record.getMessage() and JOINT_STATE_COLUMNS in record.getMessage()


def test_a_cut_file_is_read_from_its_json_messages(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    s = signals(3 * BLOCK_ROWS)
    w = LogWriter(out, meta())
    for i in range(3 * BLOCK_ROWS):
        write_cycle(w, s, i)
        if i == BLOCK_ROWS + 10:
            w.flush()  # this much survives the writer's death
    w.close_unfinished()
    got = read_run(w.part_path)
    assert got.truncated and got.messages_recovered == BLOCK_ROWS + 11
    assert np.array_equal(got.position, s["position"][: BLOCK_ROWS + 11])


def test_an_indexed_chunk_refuses_an_offset_that_is_not_the_message() -> None:
    from drivegain.formats.mcapscan import IndexedChunk

    def record(channel: int, data: bytes) -> bytes:
        return (
            struct.pack("<BQ", 0x05, 22 + len(data))
            + struct.pack("<HIQQ", channel, 0, 77, 77)
            + data
        )

    first, second = record(1, b"abc"), record(2, b"xyz")
    chunk = IndexedChunk(b"\x00" * 5 + first + second)
    at = 5 + len(first)
    chunk.add(kind=9, channel_id=1, entries=np.array([[77, 5]], dtype=np.uint64))
    assert chunk.message(9, 5, 77) == b"abc"
    # a second channel of the same kind: its entries join the first's, in file order
    chunk.add(kind=9, channel_id=2, entries=np.array([[77, at]], dtype=np.uint64))
    assert chunk.entries[9][:, 1].tolist() == [5, at] and chunk.message(9, at, 77) == b"xyz"
    chunk.add(kind=8, channel_id=2, entries=np.array([[77, at]], dtype=np.uint64))
    for kind, offset, log_time in ((9, 5, 78), (9, 0, 77), (9, 6, 77), (9, 10**6, 77), (8, 5, 77)):
        with pytest.raises(ValueError):  # (8, 5): the message there is on another channel
            chunk.message(kind, offset, log_time)
