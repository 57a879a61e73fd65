"""The batch reading of ``/joint_states`` (formats/mcapscan.py, formats/jointstates.py).

Every check compares with an independent decoding: the ``mcap`` package's own reader and
``json.loads`` of each message, so the fast path is held to what the file says.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from drivegain.errors import DataError
from drivegain.formats.jointstates import BATCH
from drivegain.formats.log import EVENTS, JOINT_STATES, RunMetadata
from drivegain.formats.logreader import iter_channel, read_run

NAMES = ["a", "b", "c"]


def _meta() -> dict[str, str]:
    return RunMetadata(
        robot="test arm",
        run="unloaded",
        payload="none",
        joint_names=NAMES,
        sync_period_s=0.001,
        started_at="2026-01-01T00:00:00Z",
    ).to_record()


def _messages(count: int, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        msg: dict = {
            "cycle": i,
            "t": i * 0.001,
            "position": rng.standard_normal(3).tolist(),
            "current_reference": rng.standard_normal(3).tolist(),
            "current": None if i % 7 == 0 else [float(x) for x in rng.standard_normal(3)],
            "setpoint": [None, 1.5, i],  # null inside a vector, an integer
            "name": NAMES,  # the optional field of contracts §4
        }
        if i % 11 == 0:
            del msg["setpoint"]  # an absent optional field
        out.append(msg)
    return out


def _write(path: Path, messages: list[dict | bytes], chunk_size: int = 64 * 1024) -> Path:
    with path.open("wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD, chunk_size=chunk_size)
        w.start()
        w.add_metadata("drivegain.run", _meta())
        sid = w.register_schema("js", "jsonschema", b"{}")
        cid = w.register_channel(JOINT_STATES, "json", sid)
        eid = w.register_channel(EVENTS, "json", sid)
        other = w.register_channel("/other", "json", sid)
        for i, m in enumerate(messages):
            data = m if isinstance(m, bytes) else json.dumps(m).encode()
            w.add_message(cid, log_time=1000 * i, data=data, publish_time=0)
            w.add_message(other, log_time=1000 * i, data=b"[1]", publish_time=0)
            if i % 1000 == 0:
                event = {"level": "info", "node": None, "code": None, "text": f"e{i}"}
                w.add_message(
                    eid, log_time=1000 * i, data=json.dumps(event).encode(), publish_time=0
                )
        w.finish()
    return path


def _independent(path: Path) -> dict[str, np.ndarray]:
    """Columns decoded with the mcap package's reader and json.loads, message by message."""
    rows: dict[str, list] = {k: [] for k in ("cycle", "t", "position", "current", "setpoint")}
    with path.open("rb") as fh:
        for _, channel, msg in make_reader(fh).iter_messages():
            if channel.topic != JOINT_STATES:
                continue
            obj = json.loads(msg.data)
            rows["cycle"].append(obj["cycle"])
            rows["t"].append(obj["t"])
            rows["position"].append(obj["position"])
            for key in ("current", "setpoint"):
                v = obj.get(key)
                rows[key].append([math.nan] * 3 if v is None else v)
    return {
        k: np.array([[math.nan if x is None else x for x in r] for r in v], dtype=float)
        if k in ("current", "setpoint")
        else np.array(v)
        for k, v in rows.items()
    }


@pytest.mark.parametrize("chunk_size", [4 * 1024, 1 << 20])
def test_batches_read_what_each_message_says(tmp_path: Path, chunk_size: int) -> None:
    count = 2 * BATCH + 123  # several batches and a partial one
    p = _write(tmp_path / "r.mcap", list(_messages(count)), chunk_size)
    log = read_run(p, n_joints=3)
    ref = _independent(p)
    assert log.messages_recovered == count and not log.truncated
    np.testing.assert_array_equal(log.cycle, ref["cycle"])
    np.testing.assert_array_equal(log.t, ref["t"])
    np.testing.assert_array_equal(log.position, ref["position"])
    np.testing.assert_array_equal(log.current, ref["current"])
    np.testing.assert_array_equal(log.setpoint, ref["setpoint"])
    assert [e["text"] for e in log.events] == [f"e{i}" for i in range(0, count, 1000)]


def test_a_bad_message_in_a_later_batch_is_named(tmp_path: Path) -> None:
    msgs: list[dict | bytes] = list(_messages(BATCH + 50))
    bad = BATCH + 17
    assert isinstance(msgs[bad], dict)
    msgs[bad]["current_reference"] = [1.0, True, 2.0]  # type: ignore[index]
    p = _write(tmp_path / "bad.mcap", msgs)
    with pytest.raises(DataError) as exc:
        read_run(p)
    text = str(exc.value)
    assert f"message {bad} (cycle {bad})" in text and "current_reference[1]" in text, text


def test_nan_tokens_and_huge_numbers_keep_their_messages(tmp_path: Path) -> None:
    msgs: list[dict | bytes] = list(_messages(300))
    msgs[120] = json.dumps({**msgs[120], "position": [0.0, math.nan, 0.0]}).encode()  # type: ignore[dict-item]
    p = _write(tmp_path / "nan.mcap", msgs)
    with pytest.raises(DataError, match=r"message 120 \(cycle 120\).*position of joint b"):
        read_run(p)
    msgs = list(_messages(300))
    text = json.dumps(msgs[40]).replace('"t": 0.04', '"t": 1' + "0" * 400, 1)
    msgs[40] = text.encode()
    p = _write(tmp_path / "huge.mcap", msgs)
    with pytest.raises(DataError, match=r"message 40 \(cycle 40\): field 't' is out of range"):
        read_run(p)


def test_iter_channel_reads_other_channels(tmp_path: Path) -> None:
    p = _write(tmp_path / "e.mcap", list(_messages(2100)))
    got = list(iter_channel(p, EVENTS))
    assert [(t, m["text"]) for t, m in got] == [
        (0, "e0"),
        (1_000_000, "e1000"),
        (2_000_000, "e2000"),
    ]
    assert sum(1 for _ in iter_channel(p, "/other")) == 2100
