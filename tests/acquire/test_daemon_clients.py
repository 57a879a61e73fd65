"""The daemon survives its clients: descriptors, connection count, idle and slow clients, deep
JSON, run requests whose checks take long, and a teardown that always stops the motion first."""

from __future__ import annotations

import errno
import json
import os
import resource
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from drivegain.acquire import request as request_module
from drivegain.acquire.daemon import Daemon, read_reply, request
from drivegain.formats.logreader import read_run


@pytest.fixture
def start_daemon(
    tmp_path: Path, daemon_kit: SimpleNamespace
) -> Iterator[Callable[..., tuple[Daemon, Path]]]:
    """Start an in-process daemon with extra ``[daemon]`` keys; stopped after the test."""
    threads: list[threading.Thread] = []
    with ExitStack() as running:

        def start(extra: str = "") -> tuple[Daemon, Path]:
            cfg, sock = daemon_kit.config(extra, sock=tmp_path / f"ctl{len(threads)}.sock")
            d = Daemon(cfg, notifier=daemon_kit.Notes())
            threads.append(running.enter_context(daemon_kit.serve(d)))
            daemon_kit.wait(lambda: "READY=1" in d.notifier.messages, what="READY=1")
            return d, sock

        yield start
    assert not any(th.is_alive() for th in threads)


def _connect(sock: Path, timeout: float = 10.0) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    s.connect(str(sock))
    return s


def _status_on(s: socket.socket) -> dict[str, Any]:
    s.sendall(b'{"cmd": "status"}\n')
    return read_reply(s)


def _read_to_end(s: socket.socket, limit: int = 1 << 26) -> bytes:
    """Everything the daemon sends until it closes (or resets) the connection."""
    data = bytearray()
    try:
        while len(data) < limit:
            chunk = s.recv(65536)
            if not chunk:
                break
            data.extend(chunk)
    except (ConnectionResetError, TimeoutError):
        pass
    return bytes(data)


# -- connections --------------------------------------------------------------------------------


def test_extra_connections_are_refused_with_one_json_line(
    start_daemon: Callable[..., tuple[Daemon, Path]], daemon_kit: SimpleNamespace
) -> None:
    d, sock = start_daemon("max_clients = 3")
    held = [_connect(sock) for _ in range(3)]
    try:
        for s in held:
            assert _status_on(s)["ok"]
        with _connect(sock) as extra:
            line = _read_to_end(extra)
        reply = json.loads(line)
        assert line.count(b"\n") == 1 and reply["ok"] is False
        assert "too many connections (3 open" in reply["error"]
        assert d.server.refused == 1
        held.pop().close()
        daemon_kit.wait(lambda: len(d.server.clients) == 2, what="the closed connection to go")
        assert request(sock, {"cmd": "status"})["ok"]
        assert all(_status_on(s)["ok"] for s in held)  # the others were never disturbed
    finally:
        for s in held:
            s.close()


def test_a_silent_connection_is_closed_after_the_idle_time_out(
    start_daemon: Callable[..., tuple[Daemon, Path]], daemon_kit: SimpleNamespace
) -> None:
    d, sock = start_daemon("client_idle_s = 0.3")
    with _connect(sock) as silent, _connect(sock) as chatty:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.0:  # talks more often than the time-out
            assert _status_on(chatty)["ok"]
            time.sleep(0.1)
        reply = json.loads(_read_to_end(silent))
        assert reply == {"ok": False, "error": "idle for more than 0.3 s: connection closed"}
        assert _status_on(chatty)["ok"]
    daemon_kit.wait(lambda: not d.server.clients, what="both connections to go")


def test_a_client_that_never_reads_its_replies_is_dropped(
    start_daemon: Callable[..., tuple[Daemon, Path]], daemon_kit: SimpleNamespace
) -> None:
    """20 000 status requests without reading: about 7 MB of replies. The daemon keeps at most
    client_buffer_bytes of them (plus what the kernel's socket buffers hold) and drops the
    client; before, it held every reply."""
    d, sock = start_daemon("client_buffer_bytes = 4096")
    line = b'{"cmd": "status"}\n'
    with _connect(sock) as flood:
        flood.setblocking(False)
        payload = memoryview(line * 20_000)
        deadline = time.monotonic() + 60
        while payload and time.monotonic() < deadline:
            try:
                payload = payload[flood.send(payload) :]
            except BlockingIOError:
                if d.server.dropped:
                    break
                time.sleep(0.01)
            except (BrokenPipeError, ConnectionResetError):
                break
        daemon_kit.wait(lambda: d.server.dropped == 1, what="the reader to be dropped")
        flood.setblocking(True)
        flood.settimeout(10)
        received = _read_to_end(flood)
    reply_size = len(json.dumps({"ok": True, **d.status()})) + 1
    assert len(received) < 3 << 20 and len(received) < 20_000 * reply_size / 2
    assert not d.server.clients
    assert request(sock, {"cmd": "status"})["ok"]


def test_deeply_nested_json_gets_a_clear_error(
    start_daemon: Callable[..., tuple[Daemon, Path]],
) -> None:
    _, sock = start_daemon()
    with _connect(sock) as s:
        for line in (b"[" * 30_000 + b"\n", b'{"cmd": "status", "x": ' + b"[" * 40 + b"\n"):
            s.sendall(line)
            reply = read_reply(s)
            assert reply["ok"] is False and "nested deeper than 32 levels" in reply["error"]
            assert "internal error" not in reply["error"]
        assert _status_on(s)["ok"]  # same connection still served


def test_accept_errors_are_survived(start_daemon: Callable[..., tuple[Daemon, Path]]) -> None:
    """accept(2) failing with EMFILE (out of descriptors) three times: logged, accepting pauses,
    the pending connection is served after; before, the error ended the daemon."""
    d, sock = start_daemon()
    real = d.server._listener
    assert real is not None

    class FlakyListener:
        failures = 3

        def accept(self) -> tuple[socket.socket, Any]:
            if self.failures:
                self.failures -= 1
                raise OSError(errno.EMFILE, "Too many open files")
            return real.accept()

        def fileno(self) -> int:
            return real.fileno()

        def close(self) -> None:
            real.close()

    d.server._listener = FlakyListener()
    reply = request(sock, {"cmd": "status"}, timeout=20)
    assert reply["ok"] and reply["state"] in ("idle", "fault")
    assert d.server.accept_errors == 3


def _daemon_process(cfg: Path, log: Path, **kw: Any) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "drivegain.cli", "daemon", "--config", str(cfg)],
        stdout=subprocess.DEVNULL,
        stderr=log.open("wb"),
        **kw,
    )


def _open_many(sock: Path, n: int) -> list[socket.socket]:
    conns = []
    for _ in range(n):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(2)
        try:
            s.connect(str(sock))
        except OSError:  # a full backlog: the daemon is not accepting (that is the point)
            s.close()
            continue
        conns.append(s)
    return conns


@pytest.mark.parametrize("how", ["limit at start", "limit lowered while idle"])
def test_out_of_file_descriptors_does_not_kill_the_daemon(
    make_config: Callable[..., Path], daemon_kit: SimpleNamespace, how: str
) -> None:
    """The measured case: ``prlimit --nofile=40`` and 35 idle connections killed the daemon
    (``OSError: [Errno 24]``). At start the daemon fits its connection limit under the
    descriptor limit; lowered under a running daemon, accept fails with EMFILE and is
    survived. Either way the daemon serves again once the clients are gone, and stops cleanly."""
    base = Path(tempfile.mkdtemp(prefix="dgfd-", dir="/tmp"))
    sock = base / "ctl.sock"
    cfg = make_config(
        daemon=f'socket = "{sock}"\noutput_dir = "{base / "runs"}"\nmax_clients = 100'
    )
    log = base / "daemon.log"

    def limit_40() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (40, 40))

    proc = _daemon_process(cfg, log, preexec_fn=limit_40 if how == "limit at start" else None)
    conns: list[socket.socket] = []
    try:
        daemon_kit.wait(lambda: sock.exists() or proc.poll() is not None, what="the socket")
        daemon_kit.wait(
            lambda: _try_status(sock) or proc.poll() is not None, what="the first status"
        )
        assert proc.poll() is None, log.read_text()
        if how != "limit at start":
            in_use = len(os.listdir(f"/proc/{proc.pid}/fd"))
            resource.prlimit(proc.pid, resource.RLIMIT_NOFILE, (in_use + 4, in_use + 4))
        conns = _open_many(sock, 35)
        time.sleep(1.0)  # the daemon meets the limit meanwhile
        assert proc.poll() is None, log.read_text()
        for s in conns:
            s.close()
        conns = []
        status = daemon_kit.wait(lambda: _try_status(sock), what="status after the flood")
        assert status["state"] in ("idle", "fault")  # a boot under load may fail
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0, log.read_text()
    finally:
        for s in conns:
            s.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = log.read_text()
    if how == "limit at start":
        assert "max_clients 100 lowered to" in text, text
    else:
        assert "cannot accept a control connection (Too many open files)" in text, text
    assert "Traceback" not in text


def _try_status(sock: Path) -> dict[str, Any] | None:
    try:
        reply = request(sock, {"cmd": "status"}, timeout=5)
    except (OSError, ValueError):
        return None
    return reply if reply.get("ok") else None


# -- run requests and teardown ------------------------------------------------------------------


def test_a_run_of_a_billion_periods_is_refused_at_once(
    start_daemon: Callable[..., tuple[Daemon, Path]], tmp_path: Path, short_trajectory: Path
) -> None:
    d, sock = start_daemon()
    doc = json.loads(short_trajectory.read_text())
    doc["periods"] = 1_000_000_000
    big = tmp_path / "big.json"
    big.write_text(json.dumps(doc))
    t0 = time.monotonic()
    reply = request(sock, {"cmd": "run", "trajectory": str(big)}, timeout=30)
    assert reply["ok"] is False and "key 'periods'" in reply["error"] and str(big) in reply["error"]
    assert time.monotonic() - t0 < 10.0  # generous: a hang is minutes
    assert request(sock, {"cmd": "status"})["state"] in ("idle", "fault") and d.runs == 0
    assert not list((tmp_path / "runs").glob("*"))


def test_long_checks_keep_the_daemon_answering_and_a_shutdown_abandons_them(
    tmp_path: Path,
    daemon_kit: SimpleNamespace,
    short_trajectory: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Checks that take long (stand-in: a check that waits) run off the loop: status answers
    "preparing", and SIGTERM ends the daemon at once, the run never started."""
    release = threading.Event()
    entered = threading.Event()
    original = request_module.check_excitation

    def slow_check(*args: Any, **kw: Any) -> None:
        entered.set()
        release.wait(120)
        original(*args, **kw)

    monkeypatch.setattr(request_module, "check_excitation", slow_check)
    cfg, sock = daemon_kit.config()
    d = Daemon(cfg, notifier=daemon_kit.Notes())
    with daemon_kit.serve(d, join_s=30) as th:
        try:
            daemon_kit.wait(lambda: "READY=1" in d.notifier.messages, what="READY=1")
            runner = _connect(sock, timeout=30)
            runner.sendall(json.dumps({"cmd": "run", "trajectory": str(short_trajectory)}).encode())
            runner.sendall(b"\n")
            assert entered.wait(30)
            status = request(sock, {"cmd": "status"}, timeout=5)
            assert status["state"] == "preparing"
            busy = request(sock, {"cmd": "run", "trajectory": str(short_trajectory)}, timeout=5)
            assert busy["ok"] is False and "being prepared" in busy["error"]
            t0 = time.monotonic()
            d.shutdown.request("SIGTERM")
            th.join(10)
            assert not th.is_alive() and time.monotonic() - t0 < 5.0
            reply = read_reply(runner)
            assert reply == {"ok": False, "error": "the daemon is shutting down"}
            runner.close()
        finally:
            release.set()  # the abandoned worker finishes its (now pointless) checks
    assert d.runs == 0 and not list((tmp_path / "runs").glob("*"))


def test_the_teardown_brings_a_run_to_rest_before_closing_the_bus(
    daemon_kit: SimpleNamespace,
    long_trajectory: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Whatever ends the loop (here an unexpected error in it, as EMFILE once was), the run is
    stopped and its session ends before the rig (CAN network) is closed."""
    cfg, sock = daemon_kit.config()
    d = Daemon(cfg, notifier=daemon_kit.Notes())
    errors: list[BaseException] = []

    def serve() -> None:
        try:
            d.serve()
        except BaseException as exc:
            errors.append(exc)

    with daemon_kit.serve(d, target=serve) as th:
        daemon_kit.wait(lambda: "READY=1" in d.notifier.messages, what="READY=1")
        reply = request(sock, {"cmd": "run", "trajectory": str(long_trajectory)})
        assert reply["ok"], reply
        daemon_kit.wait(
            lambda: d.active is not None and d.active.session.cycle > 200, what="motion"
        )
        run = d.active
        assert run is not None and d.rig is not None
        closed_while_running: list[bool] = []
        rig_close = type(d.rig).close

        def observed_close(rig: Any) -> None:
            closed_while_running.append(run.thread.is_alive())
            rig_close(rig)

        monkeypatch.setattr(type(d.rig), "close", observed_close)

        def broken_poll(timeout: float) -> None:
            raise RuntimeError("a bug in the loop")

        monkeypatch.setattr(d.server, "poll", broken_poll)
        th.join(60)
    assert not th.is_alive()
    assert len(errors) == 1 and "a bug in the loop" in str(errors[0])
    assert closed_while_running == [False]
    log = read_run(reply["out"])
    assert not log.truncated
    assert log.events[-1]["text"].startswith("operator stop (daemon teardown): robot at rest")
    assert not sock.exists()
