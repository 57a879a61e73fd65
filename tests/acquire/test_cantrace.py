"""Raw CAN traces: every frame on the channel, both directions, read back with python-can."""

from __future__ import annotations

import time
from pathlib import Path

import can
import pytest

from drivegain.acquire.cantrace import can_trace, check_trace_path, count_frames, run_trace_path
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
    # both directions are traced
    assert len(syncs) >= log.cycle.size and len(tpdos) >= log.cycle.size
    assert len(rpdos) >= log.cycle.size
    assert main([*argv, "--out", str(tmp_path / "b.mcap"), "--can-trace", str(trace)]) == 2


def test_configured_trace_is_resolved_beside_each_log(tmp_path: Path) -> None:
    """``[acquisition] can_trace``: relative to the log's folder, ``{log}`` is the log's name,
    an absolute path stays, and ``--can-trace`` (as given) wins over the configuration."""
    log = tmp_path / "runs" / "2026-a.mcap"
    assert run_trace_path(None, None, log) is None
    assert run_trace_path(None, Path("run.blf"), log) == tmp_path / "runs" / "run.blf"
    assert run_trace_path(None, Path("{log}.asc"), log) == tmp_path / "runs" / "2026-a.asc"
    assert run_trace_path(None, Path("t/{log}.log"), log) == tmp_path / "runs" / "t" / "2026-a.log"
    assert run_trace_path(None, tmp_path / "abs.blf", log) == tmp_path / "abs.blf"
    assert run_trace_path(Path("cli.log"), Path("{log}.blf"), log) == Path("cli.log")


def test_can_trace_key_records_a_trace_per_run(
    tmp_path: Path, make_config, short_trajectory: Path
) -> None:
    """`can_trace = "{log}.log"` in the TOML: each run of `drivegain acquire` gets its trace
    beside its log, named in the log, with the run's SYNCs in it; `--can-trace` overrides the
    key (no configured trace is written then)."""
    from drivegain.cli import main
    from drivegain.formats.logreader import read_run

    cfg = make_config(acquisition='can_trace = "{log}.log"')
    (tmp_path / "runs").mkdir()
    argv = ["acquire", "--config", str(cfg), "--trajectory", str(short_trajectory)]
    out = tmp_path / "runs" / "first.mcap"
    assert main([*argv, "--out", str(out)]) == 0
    trace = tmp_path / "runs" / "first.log"
    log = read_run(out)
    assert log.meta["can_trace"] == "first.log"
    with can.LogReader(str(trace)) as reader:
        syncs = sum(1 for m in reader if m.arbitration_id == 0x80)
    assert syncs >= log.cycle.size
    # the command line wins: its file is written, the configured one is not
    other, given = tmp_path / "runs" / "second.mcap", tmp_path / "given.asc"
    assert main([*argv, "--out", str(other), "--can-trace", str(given)]) == 0
    assert read_run(other).meta["can_trace"] == "given.asc"
    assert count_frames(given) > 0 and not (tmp_path / "runs" / "second.log").exists()


def test_a_fixed_trace_name_is_refused_before_boot_once_taken(
    tmp_path: Path, make_config, short_trajectory: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`can_trace = "run.blf"`: the second run would overwrite the first's trace: refused with
    exit 2 and one line naming the file and key, nothing written; a bad suffix is refused when
    the TOML is read."""
    from drivegain.cli import main

    cfg = make_config(acquisition='can_trace = "run.blf"')
    argv = ["acquire", "--config", str(cfg), "--trajectory", str(short_trajectory)]
    (tmp_path / "run.blf").write_bytes(b"the first run's trace")
    out = tmp_path / "b.mcap"
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "run.blf" in err[0] and "can_trace" in err[0], err
    assert not out.exists() and not out.with_name("b.mcap.part").exists()
    assert (tmp_path / "run.blf").read_bytes() == b"the first run's trace"

    bad = make_config(acquisition='can_trace = "run.txt"')
    argv = ["acquire", "--config", str(bad), "--trajectory", str(short_trajectory)]
    assert main([*argv, "--out", str(tmp_path / "c.mcap")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "acquisition.can_trace" in err[0] and ".txt" in err[0], err


def test_daemon_records_the_configured_trace_of_each_run(
    tmp_path: Path, make_config, short_trajectory: Path
) -> None:
    """The daemon's runs get the configured trace beside their log in ``output_dir``."""
    import threading

    from drivegain.acquire.config import load_acquisition_config
    from drivegain.acquire.daemon import Daemon, request
    from drivegain.formats.logreader import read_run

    sock, runs = tmp_path / "ctl.sock", tmp_path / "runs"
    cfg = load_acquisition_config(
        make_config(
            acquisition='can_trace = "{log}.blf"',
            daemon=f'socket = "{sock}"\noutput_dir = "{runs}"',
        )
    )

    class Quiet:
        def notify(self, state: str) -> None:
            pass

    d = Daemon(cfg, notifier=Quiet())
    th = threading.Thread(target=d.serve, name="test-daemon")
    th.start()
    try:
        deadline = time.monotonic() + 60
        while not sock.exists():
            assert time.monotonic() < deadline and th.is_alive(), "the daemon did not listen"
            time.sleep(0.05)
        reply = request(sock, {"cmd": "run", "trajectory": str(short_trajectory)})
        assert reply["ok"], reply
        while (status := request(sock, {"cmd": "status"}))["runs"] < 1:
            assert time.monotonic() < deadline + 60, "the run did not finish"
            time.sleep(0.1)
    finally:
        d.shutdown.request("test")
        th.join(30)
    assert status["last_run"]["state"] == "finished", status
    out = Path(status["last_run"]["out"])
    trace = out.with_suffix(".blf")
    assert read_run(out).meta["can_trace"] == trace.name
    with can.LogReader(str(trace)) as reader:
        assert sum(1 for m in reader if m.arbitration_id == 0x80) >= read_run(out).cycle.size


def test_trace_on_the_ipc_bus_whose_server_is_the_drives_process(
    tmp_path: Path, make_config, short_trajectory: Path
) -> None:
    """On ``drivegain-ipc`` the bus exists once the drives' process serves it: the trace joins
    then (it used to try first and fail), and holds both sides of every cycle."""
    from drivegain.cli import main
    from drivegain.formats.logreader import read_run

    cfg = make_config(
        interface="drivegain-ipc",
        acquisition="master_heartbeat_s = 2.0\nheartbeat_timeout_s = 5.0",
    )
    out, trace = tmp_path / "run.mcap", tmp_path / "run.asc"
    argv = ["acquire", "--config", str(cfg), "--trajectory", str(short_trajectory)]
    assert main([*argv, "--out", str(out), "--can-trace", str(trace)]) == 0
    log = read_run(out)
    with can.LogReader(str(trace)) as reader:
        ids = [m.arbitration_id for m in reader]
    cycles = log.cycle.size
    assert ids.count(0x80) >= cycles and ids.count(0x181) >= cycles and ids.count(0x201) >= cycles
