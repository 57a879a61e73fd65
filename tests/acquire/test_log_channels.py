"""A real (lockstep, mocked bus) acquisition's log against the schemas it declares."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import msgspec
import numpy as np
import pytest
from mcap.reader import make_reader

from drivegain.acquire.config import load_acquisition_config
from drivegain.acquire.foreground import run_foreground
from drivegain.acquire.recorder import typed_fields
from drivegain.acquire.session import RunRequest
from drivegain.drivers.exchange import RAW_FIELDS
from drivegain.formats.log import (
    EVENTS,
    JOINT_STATE_COLUMNS,
    JOINT_STATES,
    RAW,
    RAW_FIELD_DOCS,
    ROS2_JOINT_STATES,
)

jsonschema = pytest.importorskip("jsonschema", reason="jsonschema (test extra) absent")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder", reason="mcap-ros2-support absent")


def test_the_raw_schema_names_the_fields_the_drives_send() -> None:
    assert list(RAW_FIELD_DOCS) == list(RAW_FIELDS)


def test_typed_fields_turn_decimal_text_into_numbers_only() -> None:
    got = typed_fields(
        {"cycles": "802", "wall_s": "1.250", "tiny": "2e-05", "late_tpdo": "3:1,5:2",
         "hex": "0x10", "nan": "nan", "reason": "SIGTERM", "n": 7, "lead": "007"}
    )  # fmt: skip
    assert got == {
        "cycles": 802,
        "wall_s": 1.25,
        "tiny": 2e-05,
        "late_tpdo": "3:1,5:2",
        "hex": "0x10",
        "nan": "nan",
        "reason": "SIGTERM",
        "n": 7,
        "lead": "007",
    }
    assert type(got["cycles"]) is int


def test_acquired_log_follows_its_schemas(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    cfg = load_acquisition_config(make_config())
    out = tmp_path / "run.mcap"
    res = run_foreground(cfg, RunRequest(short_trajectory, out), progress=False)
    factory = mcap_ros2_decoder.DecoderFactory()
    by_topic: dict[str, list[tuple[int, int, object]]] = {}
    schemas = {}
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.message_encoding == "msgpack":  # self-describing: no schema
                assert schema is None
                by_topic.setdefault(channel.topic, []).append(
                    (message.log_time, message.sequence, msgspec.msgpack.decode(message.data))
                )
                continue
            assert schema is not None
            if channel.message_encoding == "json":
                schemas[channel.topic] = json.loads(schema.data)
                obj: object = json.loads(message.data)
            else:
                decoder = factory.decoder_for(channel.message_encoding, schema)
                assert decoder is not None
                obj = decoder(message.data)
            by_topic.setdefault(channel.topic, []).append((message.log_time, message.sequence, obj))
    assert set(by_topic) == {JOINT_STATES, RAW, EVENTS, ROS2_JOINT_STATES, JOINT_STATE_COLUMNS}
    for topic in (JOINT_STATES, RAW, EVENTS):
        validator = jsonschema.Draft202012Validator(schemas[topic])
        validator.check_schema(schemas[topic])
        for _, _, obj in by_topic[topic]:
            validator.validate(obj)
    # the raw arrays hold one integer per joint (a schema that says so is checked above; a
    # schema that said nothing would pass too, so check that it does say it)
    raw = schemas[RAW]["properties"]["raw"]["properties"]
    assert set(raw) == set(RAW_FIELDS) and all(f["minItems"] == 6 for f in raw.values())

    names = [f"j{i}" for i in range(1, 7)]
    js = by_topic[JOINT_STATES]
    ros = by_topic[ROS2_JOINT_STATES]
    assert len(js) == len(ros) == res.cycles
    for (lt_j, _, obj), (lt_r, _, msg) in zip(js, ros, strict=True):
        assert lt_j == lt_r and obj["name"] == names and list(msg.name) == names  # type: ignore[attr-defined,index]
        assert list(msg.position) == obj["position"]  # type: ignore[attr-defined,index]

    # the side channel holds the same rows, decoded here with a generic MessagePack reader
    blocks = [b for _, _, b in by_topic[JOINT_STATE_COLUMNS]]
    assert all(b["version"] == 1 and b["joints"] == 6 for b in blocks)  # type: ignore[index]
    for name, shape in (("cycle", ()), ("t", ()), ("position", (6,)), ("current", (6,))):
        dtype = "<i8" if name == "cycle" else "<f8"
        rows = np.concatenate(
            [np.frombuffer(b[name], dtype).reshape(b["rows"], *shape) for b in blocks]  # type: ignore[index]
        )
        expected = np.array(
            [np.nan if v is None else v for _, _, o in js for v in np.ravel(o[name])],  # type: ignore[index]
            dtype=dtype,
        ).reshape(len(js), *shape)
        assert np.array_equal(rows, expected, equal_nan=True), name

    events = by_topic[EVENTS]
    # events of one log time in the order of their sequence numbers (file order)
    seqs = [s for _, s, _ in events]
    assert seqs == sorted(seqs)
    stats = next(e for _, _, e in events if e["text"] == "cycle statistics")  # type: ignore[index]
    assert stats["cycles"] == res.cycles and type(stats["wall_s"]) is float  # type: ignore[index]
    started = next(e for _, _, e in events if "started" in e["text"])  # type: ignore[index,operator]
    assert type(started["duration_s"]) is float  # type: ignore[index]
