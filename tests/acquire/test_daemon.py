"""The daemon: control socket (0600, JSON lines), one run at a time, idle monitoring, systemd."""

from __future__ import annotations

import gc
import json
import os
import shutil
import signal
import socket
import stat
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from drivegain.acquire.daemon import Daemon, read_reply, request
from drivegain.acquire.session import Session
from drivegain.drivers import gcfreeze
from drivegain.formats.logreader import read_run


@pytest.fixture
def daemon(daemon_kit: SimpleNamespace) -> Iterator[tuple[Daemon, Path, Any]]:
    cfg, sock = daemon_kit.config("watchdog_s = 0.05")
    notes = daemon_kit.Notes()
    d = Daemon(cfg, notifier=notes)
    with daemon_kit.serve(d, join_s=30) as th:
        daemon_kit.wait(lambda: "READY=1" in notes.messages, what="READY=1")
        yield d, sock, notes
    assert not th.is_alive()


def test_socket_is_private_and_malformed_requests_get_errors(
    daemon: tuple[Daemon, Path, Any], daemon_kit: SimpleNamespace
) -> None:
    _, sock, notes = daemon
    mode = stat.S_IMODE(sock.stat().st_mode)
    assert stat.S_ISSOCK(sock.stat().st_mode) and mode == 0o600
    bad = [
        (b"this is not json\n", "not a JSON line"),
        (b"[1, 2]\n", "expected a JSON object"),
        (b'{"cmd": "fly"}\n', "unknown cmd 'fly'"),
        (b'{"cmd": "status", "x": 1}\n', "unknown field(s) x"),
        (b'{"cmd": "run"}\n', "'trajectory' is required"),
        (b'{"cmd": "run", "trajectory": "rel/traj.json"}\n', "must be an absolute path"),
        (b'{"cmd": "run", "trajectory": "/nope.json"}\n', "/nope.json"),
        (b'{"cmd": "run", "trajectory": "/x.json", "label": "a/b"}\n', "run label"),
        (b'{"cmd": "stop"}\n', "no run in progress"),
    ]
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(10)
        s.connect(str(sock))
        for line, message in bad:
            s.sendall(line)
            reply = read_reply(s)
            assert reply["ok"] is False and message in reply["error"], (line, reply)
        # the same connection, and the daemon, still serve
        s.sendall(b'{"cmd": "status"}\n')
        status = read_reply(s)
    assert status["ok"] and status["state"] == "idle" and status["runs"] == 0
    assert any(m.startswith("STATUS=idle") for m in notes.messages)
    daemon_kit.wait(lambda: "WATCHDOG=1" in notes.messages, what="WATCHDOG=1")


def test_one_run_at_a_time_and_stop(
    daemon: tuple[Daemon, Path, Any],
    daemon_kit: SimpleNamespace,
    long_trajectory: Path,
    short_trajectory: Path,
) -> None:
    _, sock, _ = daemon
    first = request(sock, {"cmd": "run", "trajectory": str(long_trajectory), "label": "first"})
    assert first["ok"], first
    second = request(sock, {"cmd": "run", "trajectory": str(short_trajectory), "label": "second"})
    assert second["ok"] is False and "already in progress (first)" in second["error"]
    status = daemon_kit.wait(
        lambda: (s := request(sock, {"cmd": "status"}))["run"] and s["run"]["cycle"] > 200 and s,
        what="the run to move",
    )
    assert status["state"] == "running" and status["run"]["label"] == "first"
    assert request(sock, {"cmd": "stop"}) == {"ok": True, "stopping": "first"}
    status = daemon_kit.wait(
        lambda: (s := request(sock, {"cmd": "status"}))["state"] == "idle" and s, what="idle"
    )
    last = status["last_run"]
    assert last["state"] == "stopped" and last["stop_reason"] == "stop request"
    log = read_run(last["out"])
    assert log.meta["run"] == "first" and not log.truncated
    assert log.events[-1]["text"].startswith("operator stop (stop request): robot at rest")
    # and the next run is accepted and completes
    again = request(sock, {"cmd": "run", "trajectory": str(short_trajectory)})
    assert again["ok"] and again["label"] == "unloaded"
    status = daemon_kit.wait(
        lambda: (s := request(sock, {"cmd": "status"}))["runs"] == 2 and s, what="second run"
    )
    assert status["last_run"]["state"] == "finished"


def test_idle_monitoring_notices_lost_drives_and_recovers(
    daemon: tuple[Daemon, Path, Any], daemon_kit: SimpleNamespace, short_trajectory: Path
) -> None:
    d, sock, notes = daemon
    assert d.rig is not None and d.rig.cell is not None
    d.rig.cell.stop()  # the drives lose power: no more heartbeats
    status = daemon_kit.wait(
        lambda: (s := request(sock, {"cmd": "status"}))["state"] == "fault" and s,
        what="the idle fault",
    )
    assert "heartbeat" in status["fault"]
    assert any(m.startswith("STATUS=fault") for m in notes.messages)
    # a run request boots the cell again
    reply = request(sock, {"cmd": "run", "trajectory": str(short_trajectory)})
    assert reply["ok"], reply
    status = daemon_kit.wait(
        lambda: (s := request(sock, {"cmd": "status"}))["runs"] == 1 and s, what="the run"
    )
    assert status["state"] == "idle" and status["last_run"]["state"] == "finished"


def _as_nobody(python: str, code: str) -> subprocess.CompletedProcess[bytes]:
    """Run the Python ``code`` as the user nobody (65534), with the system's ``python``."""
    return subprocess.run(
        [python, "-c", code],
        user=65534,
        cwd="/",
        env={"PATH": "/usr/bin:/bin"},
        capture_output=True,
        timeout=30,
    )


def test_service_process_systemd_protocol_and_other_users(
    make_config: Callable[..., Path],
) -> None:
    """The real command: sd_notify over NOTIFY_SOCKET, JSON logs, SIGTERM, other uids refused."""
    base = Path(tempfile.mkdtemp(prefix="dgd-", dir="/tmp"))
    os.chmod(base, 0o755)  # others may reach the socket file: only its own mode keeps them out
    sock = base / "ctl.sock"
    cfg = make_config(
        daemon=f'socket = "{sock}"\noutput_dir = "{base / "runs"}"\nlog_format = "json"'
    )
    notify_path = base / "notify.sock"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.settimeout(30)
    env = dict(os.environ, NOTIFY_SOCKET=str(notify_path), WATCHDOG_USEC="200000")
    env.pop("WATCHDOG_PID", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "drivegain.cli", "daemon", "--config", str(cfg)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    got: list[str] = []
    try:
        while "READY=1" not in got:
            got.append(notify.recv(4096).decode())
        while "WATCHDOG=1" not in got:
            got.append(notify.recv(4096).decode())
        assert stat.S_IMODE(sock.stat().st_mode) == 0o600
        assert request(sock, {"cmd": "status"})["state"] == "idle"
        system_python = shutil.which("python3", path="/usr/bin:/bin")
        if os.getuid() == 0 and system_python:
            # another user (nobody) on the same machine
            other = _as_nobody(
                system_python,
                f"import socket; s = socket.socket(socket.AF_UNIX); s.connect({str(sock)!r})",
            )
            assert other.returncode != 0 and b"PermissionError" in other.stderr
            # even with the file mode opened up, the daemon checks the peer's uid itself
            os.chmod(sock, 0o666)
            other = _as_nobody(
                system_python,
                "import socket; s = socket.socket(socket.AF_UNIX); "
                f"s.connect({str(sock)!r}); print(s.recv(4096).decode())",
            )
            assert json.loads(other.stdout) == {"ok": False, "error": "permission denied"}
            os.chmod(sock, 0o600)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
        while "STOPPING=1" not in got:
            got.append(notify.recv(4096).decode())
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        notify.close()
    assert proc.returncode == 0, err.decode()
    assert not sock.exists()
    records = [json.loads(line) for line in err.decode().splitlines() if line.startswith("{")]
    assert any(r.get("event") == "ready" and r["level"] == "info" for r in records)
    assert any(r.get("event") == "stopped" for r in records)
    assert any(m.startswith("STATUS=") for m in got)


def test_shutdown_during_a_run_brings_it_to_rest_first(
    daemon_kit: SimpleNamespace, long_trajectory: Path
) -> None:
    cfg, sock = daemon_kit.config()
    d = Daemon(cfg, notifier=daemon_kit.Notes())
    with daemon_kit.serve(d, stop="SIGTERM") as th:  # what systemctl stop sends
        daemon_kit.wait(lambda: sock.exists(), what="the socket")
        daemon_kit.wait(lambda: d.rig is not None and d.rig.master is not None, what="the boot")
        reply = request(sock, {"cmd": "run", "trajectory": str(long_trajectory)})
        assert reply["ok"], reply
        daemon_kit.wait(
            lambda: d.active is not None and d.active.session.cycle > 200, what="motion"
        )
    assert not th.is_alive() and not sock.exists()
    log = read_run(reply["out"])
    assert not log.truncated
    assert log.events[-1]["text"].startswith("operator stop (SIGTERM): robot at rest")


def test_the_freeze_is_held_through_every_run_and_released_when_the_daemon_closes(
    daemon_kit: SimpleNamespace,
    short_trajectory: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The rig holds the garbage-collector freeze from boot to close: a run does not end it
    (a session once unfroze the process after its run while the master believed it held it)."""
    base = gcfreeze.holders()
    seen: dict[str, list[tuple[int, int]]] = {"run": [], "idle": []}
    original = Session._loop

    def observed_loop(self: Session, *args: Any) -> None:
        # on the cycle thread, at the first cycle and after the last: during the run
        seen["run"].append((gcfreeze.holders(), gc.get_freeze_count()))
        original(self, *args)
        seen["run"].append((gcfreeze.holders(), gc.get_freeze_count()))

    monkeypatch.setattr(Session, "_loop", observed_loop)
    cfg, sock = daemon_kit.config()
    d = Daemon(cfg, notifier=daemon_kit.Notes())
    with daemon_kit.serve(d) as th:
        daemon_kit.wait(lambda: d.rig is not None and d.rig.master is not None, what="the boot")
        daemon_kit.wait(lambda: sock.exists(), what="the socket")
        for runs in (1, 2):
            reply = request(sock, {"cmd": "run", "trajectory": str(short_trajectory)})
            assert reply["ok"], reply
            status = daemon_kit.wait(
                lambda n=runs: (s := request(sock, {"cmd": "status"}))["runs"] == n and s,
                what=f"run {runs}",
            )
            assert status["state"] == "idle" and status["last_run"]["state"] == "finished"
            # between runs the daemon watches the drives: still frozen
            seen["idle"].append((gcfreeze.holders(), gc.get_freeze_count()))
    assert not th.is_alive()
    assert len(seen["run"]) == 4 and len(seen["idle"]) == 2, seen
    assert all(held > base and frozen > 0 for held, frozen in seen["run"] + seen["idle"]), seen
    assert gcfreeze.holders() == base  # released with the rig
    if base == 0:
        assert gc.get_freeze_count() == 0
