"""Raw CAN traces: every frame on the channel, both directions, read back with python-can."""

from __future__ import annotations

import time
from pathlib import Path

import can
import pytest

from drivegain.acquire.cantrace import can_trace, check_trace_path, count_frames
from drivegain.drivers.bus import BusConfig, open_bus
from drivegain.errors import InputError


@pytest.mark.parametrize("suffix", [".blf", ".asc", ".log"])
def test_trace_holds_every_frame_of_both_sides(tmp_path: Path, suffix: str) -> None:
    cfg = BusConfig(interface="virtual", channel=f"trace-{suffix[1:]}")
    path = check_trace_path(tmp_path / f"run{suffix}")
    sent: list[tuple[int, bytes]] = []
    with can_trace(cfg, path):
        master, drive = open_bus(cfg), open_bus(cfg)
        try:
            for k in range(50):
                a = can.Message(arbitration_id=0x80, data=bytes([k]), is_extended_id=False)
                b = can.Message(arbitration_id=0x181, data=bytes(range(8)), is_extended_id=False)
                master.send(a)
                drive.send(b)
                sent += [(a.arbitration_id, bytes(a.data)), (b.arbitration_id, bytes(b.data))]
            deadline = time.monotonic() + 10.0  # against a hang only
            while time.monotonic() < deadline and drive.recv(0.0) is not None:
                pass
            time.sleep(0.2)  # the trace's reader thread drains its queue
        finally:
            master.shutdown()
            drive.shutdown()
    assert count_frames(path) == len(sent)
    with can.LogReader(str(path)) as reader:
        seen = [(m.arbitration_id, bytes(m.data)) for m in reader]
    assert seen == sent


def test_trace_name_is_checked(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="unknown trace format"):
        check_trace_path(tmp_path / "run.txt")
    (tmp_path / "old.blf").write_bytes(b"x")
    with pytest.raises(InputError, match="refusing to overwrite"):
        check_trace_path(tmp_path / "old.blf")


def test_acquire_records_a_trace_beside_the_log(
    tmp_path: Path, make_config, short_trajectory: Path
) -> None:
    """`drivegain acquire --can-trace`: every SYNC of the run is in the trace, the trace is named
    in the log's metadata, and python-can reads it."""
    from drivegain.cli import main
    from drivegain.formats.logreader import read_run

    out, trace = tmp_path / "run.mcap", tmp_path / "run.log"
    argv = ["acquire", "--config", str(make_config()), "--trajectory", str(short_trajectory)]
    assert main([*argv, "--out", str(out), "--can-trace", str(trace)]) == 0
    log = read_run(out)
    assert log.meta["can_trace"] == "run.log"
    with can.LogReader(str(trace)) as reader:
        frames = list(reader)
    syncs = [m for m in frames if m.arbitration_id == 0x80]
    rpdos = [m for m in frames if m.arbitration_id == 0x201]
    tpdos = [m for m in frames if m.arbitration_id == 0x181]
    assert len(syncs) >= log.n and len(tpdos) >= log.n  # both directions are traced
    assert len(rpdos) >= log.n
    assert main([*argv, "--out", str(tmp_path / "b.mcap"), "--can-trace", str(trace)]) == 2
