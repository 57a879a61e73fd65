"""The long-running acquisition service behind a Unix control socket.

Protocol: one JSON object per line, one reply line per request.

- ``{"cmd": "status"}`` → ``{"ok": true, "state": "idle" | "running" | "fault", ...}``
- ``{"cmd": "run", "trajectory": "/abs/traj.json", "label": "unloaded", "payload": null}``
  → ``{"ok": true, "out": "/.../20250101T120000Z-unloaded.mcap", ...}``; refused while a run is
  in progress.
- ``{"cmd": "stop"}`` → the run in progress decelerates to rest and finishes its log.

A malformed request gets ``{"ok": false, "error": "..."}`` and the daemon keeps serving. The
socket is created with permissions 0600 (owner only) and a peer of another user is refused.
While idle the daemon watches the drives (heartbeats, EMCY) through :meth:`Master.check`.
systemd ``Type=notify``: READY=1 once the drives are booted and the socket listens, STATUS=
on every change, WATCHDOG=1 at half of ``WATCHDOG_USEC`` while the service is healthy.
"""

from __future__ import annotations

import json
import logging
import os
import selectors
import socket
import struct
import threading
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

from drivegain import __version__
from drivegain.acquire.config import AcquisitionConfig, DaemonSettings
from drivegain.acquire.request import RunRequest, prepare_run
from drivegain.acquire.request import validate_label as _validate_label
from drivegain.acquire.rig import Rig
from drivegain.acquire.session import RunResult, RunState, Session
from drivegain.acquire.stop import StopRequest
from drivegain.errors import ConfigError, DrivegainError, InputError
from drivegain.unixsock import NotASocket, SocketInUse, bind_private

log = logging.getLogger(__name__)

MAX_LINE = 64 * 1024
_CYCLING = {RunState.APPROACH, RunState.EXCITATION, RunState.RETREAT, RunState.STOPPING}


class Notifier(Protocol):
    """What the daemon needs from ``sdnotify.SystemdNotifier``."""

    def notify(self, state: str) -> None: ...


class RequestError(InputError):
    """A control request that cannot be served (the reply carries the message)."""


@dataclass
class _Client:
    sock: socket.socket
    buffer: bytearray = field(default_factory=bytearray)
    out: bytearray = field(default_factory=bytearray)
    closing: bool = False


@dataclass
class _ActiveRun:
    session: Session
    thread: threading.Thread
    stop: StopRequest
    out: Path
    outcome: dict[str, Any] = field(default_factory=dict)
    last_cycle: int = -1
    last_progress: float = field(default_factory=time.monotonic)


def default_notifier() -> Notifier:
    """systemd's notification socket (does nothing outside systemd)."""
    import sdnotify

    notifier: Notifier = sdnotify.SystemdNotifier()
    return notifier


def watchdog_interval(settings: DaemonSettings) -> float | None:
    """Seconds between WATCHDOG=1 pings: half of systemd's ``WATCHDOG_USEC``, else the config."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if usec and (not pid or pid == str(os.getpid())):
        try:
            return max(int(usec) / 2e6, 0.01)
        except ValueError:
            log.warning("ignoring WATCHDOG_USEC=%r", usec)
    return settings.watchdog_s


class Daemon:
    """The acquisition service.

    Parameters
    ----------
    cfg
        Acquisition configuration with a ``[daemon]`` table.
    notifier
        systemd notifier (tests pass their own).
    """

    def __init__(self, cfg: AcquisitionConfig, notifier: Notifier | None = None):
        if cfg.daemon is None:
            raise ConfigError("a [daemon] table is needed to run the daemon", file=cfg.source)
        self.cfg = cfg
        self.settings = cfg.daemon
        self.notifier = notifier if notifier is not None else default_notifier()
        self.shutdown = StopRequest()
        self.rig: Rig | None = None
        self.fault: str | None = None
        self.active: _ActiveRun | None = None
        self.last_run: dict[str, Any] | None = None
        self.runs = 0
        self._listener: socket.socket | None = None
        self._selector = selectors.DefaultSelector()
        self._clients: dict[int, _Client] = {}
        self._status_text = ""
        self._uid = os.getuid()

    # -- lifecycle -----------------------------------------------------------------------------

    def serve(self) -> int:
        """Boot the drives, listen, serve until SIGTERM/SIGINT (``shutdown`` request); exit code."""
        out_dir = self.settings.output_dir
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(
                f"cannot create output_dir {out_dir}: {exc.strerror}",
                file=self.cfg.source,
                key="daemon.output_dir",
            ) from None
        self._listen()
        try:
            self._boot()
            self._notify("READY=1")
            log.info(
                "daemon ready",
                extra={"event": "ready", "socket": str(self.settings.socket), "pid": os.getpid()},
            )
            self._loop()
        finally:
            self._notify("STOPPING=1")
            self._teardown()
        return 0

    def _boot(self) -> None:
        self.rig = Rig(self.cfg)
        try:
            self.rig.open()
            self.fault = None
        except DrivegainError as exc:
            # a daemon survives a cell that is off: it reports and retries on the next run
            self.fault = f"boot failed: {exc}"
            self.rig = None
            log.error("drives did not boot: %s", exc, extra={"event": "fault"})
        self._update_status()

    def _listen(self) -> None:
        path = self.settings.socket
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        try:
            listener = bind_private(path, socket.SOCK_STREAM)
        except NotASocket:
            raise ConfigError(
                f"{path} exists and is not a socket", file=self.cfg.source, key="daemon.socket"
            ) from None
        except SocketInUse:
            raise ConfigError(
                f"another daemon is listening on {path}", file=self.cfg.source, key="daemon.socket"
            ) from None
        listener.listen(8)
        listener.setblocking(False)
        self._selector.register(listener, selectors.EVENT_READ, None)
        self._listener = listener

    def _teardown(self) -> None:
        for client in list(self._clients.values()):
            self._close_client(client)
        if self._listener is not None:
            self._selector.unregister(self._listener)
            self._listener.close()
            self._listener = None
            try:
                self.settings.socket.unlink()
            except OSError:
                pass
        if self.rig is not None:
            self.rig.close()
            self.rig = None
        self._selector.close()
        log.info("daemon stopped", extra={"event": "stopped"})

    # -- main loop -----------------------------------------------------------------------------

    def _loop(self) -> None:
        wd = watchdog_interval(self.settings)
        next_wd = time.monotonic()
        next_check = time.monotonic()
        forwarded = 0
        while True:
            if self.shutdown.requested:
                if self.active is None:
                    return
                # forward every signal to the run: the first stops smoothly, a second quick-stops
                while forwarded < self.shutdown.count:
                    self.active.stop.request(self.shutdown.reason or "shutdown")
                    forwarded += 1
            timeout = self.settings.idle_check_s
            for key, mask in self._selector.select(timeout):
                if key.data is None:
                    self._accept()
                else:
                    self._service(key.data, mask)
            self._reap_run()
            now = time.monotonic()
            if self.active is None and now >= next_check:
                next_check = now + self.settings.idle_check_s
                self._idle_check()
            if wd is not None and now >= next_wd:
                next_wd = now + wd
                if self._healthy(now):
                    self._notify("WATCHDOG=1")
            self._update_status()

    def _healthy(self, now: float) -> bool:
        """False when a run's cycle loop has not advanced for 5 s while it should be cycling."""
        run = self.active
        if run is None:
            return True
        if run.session.cycle != run.last_cycle:
            run.last_cycle = run.session.cycle
            run.last_progress = now
            return True
        return run.session.state not in _CYCLING or now - run.last_progress < 5.0

    def _idle_check(self) -> None:
        if self.rig is None or self.rig.master is None:
            return
        master = self.rig.master
        try:
            master.check()
            for ev in master.drain_events():
                log.info(
                    "node %s: %s",
                    ev.node,
                    ev.text,
                    extra={"event": "drive", "node": ev.node, "code": ev.code, "level": ev.level},
                )
        except DrivegainError as exc:
            if self.fault is None:
                log.error(
                    "drive fault while idle: %s",
                    exc,
                    extra={
                        "event": "fault",
                        "node": getattr(exc, "node", None),
                        "code": getattr(exc, "code", None),
                    },
                )
            self.fault = str(exc)
            # the cell is in an unknown state: release it; the next run boots it again
            self.rig.close()
            self.rig = None

    # -- sockets -------------------------------------------------------------------------------

    def _accept(self) -> None:
        assert self._listener is not None
        try:
            sock, _ = self._listener.accept()
        except BlockingIOError:
            return
        uid = _peer_uid(sock)
        if uid is not None and uid not in (self._uid, 0):
            log.warning(
                "refused a connection from uid %d", uid, extra={"event": "refused", "uid": uid}
            )
            try:
                sock.sendall(_encode({"ok": False, "error": "permission denied"}))
            except OSError:
                pass
            sock.close()
            return
        sock.setblocking(False)
        client = _Client(sock)
        self._clients[sock.fileno()] = client
        self._selector.register(sock, selectors.EVENT_READ, client)

    def _service(self, client: _Client, mask: int) -> None:
        if mask & selectors.EVENT_READ:
            try:
                data = client.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                data = None
            except OSError:
                data = b""
            if data == b"":
                self._close_client(client)
                return
            if data:
                client.buffer.extend(data)
                while b"\n" in client.buffer:
                    line, _, rest = bytes(client.buffer).partition(b"\n")
                    client.buffer = bytearray(rest)
                    client.out.extend(_encode(self.handle_line(line)))
                if len(client.buffer) > MAX_LINE:
                    client.out.extend(
                        _encode({"ok": False, "error": f"request longer than {MAX_LINE} bytes"})
                    )
                    client.closing = True
                    client.buffer.clear()
        if client.out:
            try:
                sent = client.sock.send(client.out)
                del client.out[:sent]
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                self._close_client(client)
                return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.out else 0)
        if client.closing and not client.out:
            self._close_client(client)
            return
        self._selector.modify(client.sock, events, client)

    def _close_client(self, client: _Client) -> None:
        self._clients.pop(client.sock.fileno(), None)
        try:
            self._selector.unregister(client.sock)
        except (KeyError, ValueError):
            pass
        client.sock.close()

    # -- requests ------------------------------------------------------------------------------

    def handle_line(self, line: bytes) -> dict[str, Any]:
        """The reply to one request line (never raises)."""
        try:
            try:
                req = json.loads(line.decode("utf-8"))
            except (UnicodeDecodeError, ValueError) as exc:
                raise RequestError(f"malformed request: not a JSON line ({exc})") from None
            if not isinstance(req, dict):
                raise RequestError("malformed request: expected a JSON object")
            cmd = req.get("cmd")
            if cmd == "status":
                _only(req, {"cmd"})
                return {"ok": True, **self.status()}
            if cmd == "run":
                _only(req, {"cmd", "trajectory", "label", "payload"})
                return {"ok": True, **self.start_run(req)}
            if cmd == "stop":
                _only(req, {"cmd"})
                return {"ok": True, **self.stop_run()}
            raise RequestError(
                f"malformed request: unknown cmd {cmd!r} (expected status, run or stop)"
            )
        except InputError as exc:
            log.warning("request refused: %s", exc, extra={"event": "refused"})
            return {"ok": False, "error": str(exc)}
        except DrivegainError as exc:
            log.error("request failed: %s", exc, extra={"event": "error"})
            return {"ok": False, "error": str(exc)}
        except Exception as exc:  # a bug must not take the service down
            log.exception("internal error serving a request")
            return {"ok": False, "error": f"internal error: {type(exc).__name__}: {exc}"}

    def status(self) -> dict[str, Any]:
        """What ``status`` replies."""
        run = None
        if self.active is not None:
            s = self.active.session
            run = {
                "label": s.prepared.label,
                "state": s.state.value,
                "cycle": s.cycle,
                "t": round(s.t, 4),
                "duration_s": round(s.duration_s, 4),
                "out": str(self.active.out),
            }
        state = "running" if self.active is not None else ("fault" if self.fault else "idle")
        return {
            "state": state,
            "run": run,
            "last_run": self.last_run,
            "fault": self.fault,
            "runs": self.runs,
            "pid": os.getpid(),
            "version": __version__,
            "clock": self.cfg.clock,
            "period_s": self.cfg.period_s,
        }

    def start_run(self, req: dict[str, Any]) -> dict[str, Any]:
        """Check and start a run (the ``run`` request)."""
        if self.active is not None:
            raise RequestError(
                f"a run is already in progress ({self.active.session.prepared.label}): "
                "send stop or wait"
            )
        if self.shutdown.requested:
            raise RequestError("the daemon is shutting down")
        trajectory = _abs_path(req, "trajectory", required=True)
        assert trajectory is not None
        payload = _abs_path(req, "payload", required=False)
        label = req.get("label")
        if label is not None and not isinstance(label, str):
            raise RequestError("malformed request: 'label' must be a string", key="label")
        if label is not None:
            _validate_label(label)
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
        name = label or ("loaded" if payload is not None else "unloaded")
        out = self.settings.output_dir / f"{stamp}-{name}.mcap"
        prepared = prepare_run(
            self.cfg, RunRequest(trajectory=trajectory, out=out, label=label, payload=payload)
        )
        if self.rig is None:
            log.info("booting the drives again", extra={"event": "boot"})
            self._boot()
            if self.rig is None:
                raise DrivegainError(f"the drives are not available: {self.fault}")
        assert self.rig.master is not None
        stop = StopRequest()
        session = Session(
            self.cfg,
            self.rig.master,
            prepared,
            stop=stop,
            pre_events=self.rig.boot_events,
            policy=self.rig.policy,
        )
        self.rig.boot_events = []
        session.plan()
        run = _ActiveRun(session=session, thread=threading.Thread(), stop=stop, out=out)

        def target() -> None:
            try:
                run.outcome["result"] = session.run()
            except BaseException as exc:
                run.outcome["error"] = exc

        run.thread = threading.Thread(target=target, name="drivegain-cycle", daemon=True)
        self.active = run
        self.fault = None
        run.thread.start()
        log.info(
            "run started",
            extra={"event": "run", "label": prepared.label, "out": str(out)},
        )
        return {"label": prepared.label, "out": str(out), "duration_s": session.duration_s}

    def stop_run(self) -> dict[str, Any]:
        """Ask the run in progress to come to rest (the ``stop`` request)."""
        if self.active is None:
            raise RequestError("no run in progress")
        self.active.stop.request("stop request")
        log.info("stop requested", extra={"event": "stop"})
        return {"stopping": self.active.session.prepared.label}

    def _reap_run(self) -> None:
        run = self.active
        if run is None or run.thread.is_alive():
            return
        run.thread.join()
        self.active = None
        self.runs += 1
        res: RunResult | None = run.outcome.get("result") or run.session.result
        err = run.outcome.get("error")
        self.last_run = {
            "label": run.session.prepared.label,
            "state": res.state.value if res else "fault",
            "cycles": res.cycles if res else run.session.cycle,
            "out": str(res.path) if res and res.path else None,
            "fault": str(err) if err else None,
            "stop_reason": res.stop_reason if res else None,
        }
        if err is not None:
            self.fault = str(err)
            log.error(
                "run ended with a fault: %s",
                err,
                extra={"event": "fault", "out": self.last_run["out"]},
            )
            # the drives were quick-stopped; boot them again before the next run
            if self.rig is not None:
                self.rig.close()
                self.rig = None
        else:
            log.info("run ended", extra={"event": "run_end", **self.last_run})

    def _update_status(self) -> None:
        if self.active is not None:
            s = self.active.session
            text = f"running {s.prepared.label}: {s.state.value} t={s.t:.1f}/{s.duration_s:.1f} s"
        elif self.fault:
            text = f"fault: {self.fault}"
        else:
            text = f"idle, {self.runs} runs"
        if text != self._status_text:
            # one STATUS per change: systemd shows it in `systemctl status`
            self._status_text = text
            self._notify(f"STATUS={text[:200]}")

    def _notify(self, state: str) -> None:
        try:
            self.notifier.notify(state)
        except Exception as exc:
            log.debug("sd_notify failed: %s", exc)


def _only(req: dict[str, Any], allowed: set[str]) -> None:
    extra = sorted(set(req) - allowed)
    if extra:
        raise RequestError(f"malformed request: unknown field(s) {', '.join(extra)}")


def _abs_path(req: dict[str, Any], key: str, *, required: bool) -> Path | None:
    value = req.get(key)
    if value is None:
        if required:
            raise RequestError(f"malformed request: '{key}' is required", key=key)
        return None
    if not isinstance(value, str) or not value:
        raise RequestError(f"malformed request: '{key}' must be a path string", key=key)
    path = Path(value)
    if not path.is_absolute():
        raise RequestError(
            f"'{key}' must be an absolute path (the daemon's working directory is not yours)",
            key=key,
        )
    return path


def _encode(obj: dict[str, Any]) -> bytes:
    return (json.dumps(obj, default=str) + "\n").encode()


def _peer_uid(sock: socket.socket) -> int | None:
    """The uid of the process at the other end (Linux SO_PEERCRED), or None if unknown."""
    try:
        creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    except (OSError, AttributeError):
        return None
    _pid, uid, _gid = struct.unpack("3i", creds)
    return int(uid)


def request(path: str | Path, message: dict[str, Any], timeout: float = 10.0) -> dict[str, Any]:
    """Send one request to a daemon and return its reply (a small client for scripts and tests).

    Raises
    ------
    OSError
        The socket cannot be reached.
    """
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        s.connect(str(path))
        s.sendall(_encode(message))
        return read_reply(s)


def read_reply(s: socket.socket) -> dict[str, Any]:
    """Read one reply line from a connected control socket."""
    buf = bytearray()
    while b"\n" not in buf:
        chunk = s.recv(65536)
        if not chunk:
            raise ConnectionError("the daemon closed the connection")
        buf.extend(chunk)
    reply: dict[str, Any] = json.loads(bytes(buf).partition(b"\n")[0])
    return reply
