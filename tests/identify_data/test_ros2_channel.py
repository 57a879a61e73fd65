"""The ROS 2 ``sensor_msgs/msg/JointState`` channel, decoded by ``mcap_ros2`` (not by our code)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from drivegain.formats.log import JOINT_STATES, ROS2_JOINT_STATES, RunMetadata
from drivegain.formats.logreader import read_run
from drivegain.formats.logwriter import write_run

mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder", reason="mcap-ros2-support absent")

NAMES = ["base", "shoulder", "elbow", "wrist_1"]


def _meta() -> RunMetadata:
    return RunMetadata(
        robot="arm",
        run="unloaded",
        payload="none",
        joint_names=NAMES,
        sync_period_s=0.004,
        started_at="2026-03-01T10:00:00.000Z",
    )


def _signals(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(11)
    t = np.arange(n) * 0.004
    pos = rng.uniform(-3, 3, (n, len(NAMES)))
    ref = rng.uniform(-2, 2, (n, len(NAMES)))
    return t, pos, ref


def _decoded(path: Path) -> tuple[list[tuple[int, dict]], list[tuple[int, object, object]]]:
    """(log time, JSON message) of /joint_states and (log time, channel, ROS 2 message)."""
    factory = mcap_ros2_decoder.DecoderFactory()
    js, ros = [], []
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[factory])
        for schema, channel, message in reader.iter_messages(
            topics=[JOINT_STATES, ROS2_JOINT_STATES]
        ):
            if channel.topic == JOINT_STATES:
                js.append((message.log_time, json.loads(message.data)))
            else:
                assert schema is not None
                assert (schema.name, schema.encoding) == ("sensor_msgs/msg/JointState", "ros2msg")
                assert channel.message_encoding == "cdr"
                decoder = factory.decoder_for(channel.message_encoding, schema)
                assert decoder is not None
                ros.append((message.log_time, channel, decoder(message.data)))
    return js, ros


def test_ros2_joint_states_match_the_json_channel(tmp_path: Path) -> None:
    t, pos, ref = _signals(300)
    gains = np.array([30.0, -12.5, 8.25, 1.5])
    path = write_run(
        tmp_path / "r.mcap",
        _meta(),
        t,
        pos,
        ref,
        log_time_ns=1_700_000_000_000_000_000 + np.arange(300) * 4_000_000,
        effort_gains=gains,
    )
    js, ros = _decoded(path)
    assert len(js) == len(ros) == 300
    for (lt_j, obj), (lt_r, channel, msg) in zip(js, ros, strict=True):
        assert lt_j == lt_r
        assert obj["name"] == NAMES and list(msg.name) == NAMES
        # the stamp is the log time, split as builtin_interfaces/Time
        assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == lt_r
        assert msg.header.stamp.nanosec < 1_000_000_000
        assert list(msg.position) == obj["position"]  # float64 both ways: exact
        assert list(msg.velocity) == []
        np.testing.assert_array_equal(
            msg.effort, np.array(obj["current_reference"]) * gains
        )  # N·m = A × N·m/A
        assert "N·m" in channel.metadata["effort"]
    np.testing.assert_array_equal(np.array([m.position for _, _, m in ros]), pos)
    # the contract's reader is unaffected by the extra channel and the extra field
    np.testing.assert_array_equal(read_run(path).position, pos)


def test_without_gains_the_efforts_are_empty_and_say_why(tmp_path: Path) -> None:
    t, pos, ref = _signals(20)
    path = write_run(tmp_path / "r.mcap", _meta(), t, pos, ref)
    _, ros = _decoded(path)
    assert len(ros) == 20
    assert all(list(m.effort) == [] for _, _, m in ros)
    assert "does not know the drive gains" in ros[0][1].metadata["effort"]
