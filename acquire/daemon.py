"""The long-running acquisition service behind a Unix control socket.

Protocol: one JSON object per line, one reply line per request, in order.

- ``{"cmd": "status"}`` → ``{"ok": true, "state": "idle" | "preparing" | "running" | "fault",
  ...}``
- ``{"cmd": "run", "trajectory": "/abs/traj.json", "label": "unloaded", "payload": null}``
  → ``{"ok": true, "out": "/.../20250101T120000Z-unloaded.mcap", ...}`` once the request's
  checks passed and the motion is planned; refused while a run is prepared or in progress.
- ``{"cmd": "stop"}`` → the run in progress decelerates to rest and finishes its log (a run
  still under its checks is abandoned).

A malformed request gets ``{"ok": false, "error": "..."}`` and the daemon keeps serving. The
connections and their limits (count, idle time-out, reply buffers, accept errors) are
:mod:`.control`'s. The checks of a ``run`` (files, limits of the trajectory and payload) run on a
worker thread before any drive is touched, so the loop keeps answering and a SIGTERM is honoured
at once (the checks are abandoned). While idle the daemon watches the drives (heartbeats, EMCY)
through :meth:`Master.check`. Whatever ends the service, a run in progress is brought to rest
before the drives and the bus are closed. systemd ``Type=notify``: READY=1 once the drives are
booted and the socket listens, STATUS= on every change, WATCHDOG=1 at half of ``WATCHDOG_USEC``
while the service is healthy.
"""

from __future__ import annotations

import logging
import os
import shlex
import threading
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

from drivegain import __version__
from drivegain.acquire.cantrace import can_trace
from drivegain.acquire.config import AcquisitionConfig, DaemonSettings
from drivegain.acquire.control import Client, ControlServer, RequestError, parse_request
from drivegain.acquire.control import read_reply as read_reply
from drivegain.acquire.control import request as request
from drivegain.acquire.foreground import run_session
from drivegain.acquire.recorder import discard_unrecorded
from drivegain.acquire.request import PrepareJob, RunRequest
from drivegain.acquire.request import validate_label as _validate_label
from drivegain.acquire.rig import Rig
from drivegain.acquire.session import RunResult, RunState, Session
from drivegain.acquire.stop import StopRequest
from drivegain.errors import ConfigError, DrivegainError, InputError

log = logging.getLogger(__name__)

_CYCLING = {RunState.APPROACH, RunState.EXCITATION, RunState.RETREAT, RunState.STOPPING}
#: How long the teardown waits for a run to come to rest after a stop request, s, before it
#: asks for a quick stop (then as long again before closing regardless).
STOP_WAIT_S = 15.0


class Notifier(Protocol):
    """What the daemon needs from ``sdnotify.SystemdNotifier``."""

    def notify(self, state: str) -> None: ...


@dataclass
class _Preparing:
    """A ``run`` request under its checks on a worker (:class:`PrepareJob`)."""

    job: PrepareJob
    client: Client | None
    label: str


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
        self.preparing: _Preparing | None = None
        self.last_run: dict[str, Any] | None = None
        self.runs = 0
        self.server = ControlServer(self.settings, self._handle, cfg.source)
        self._status_text = ""

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
        self.server.listen()
        try:
            self._boot()
            self._notify("READY=1")
            sock = os.path.abspath(self.settings.socket)
            log.info(
                "daemon ready: control socket %s (try: drivegain ctl status --socket %s)",
                sock,
                shlex.quote(sock),
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

    def _teardown(self) -> None:
        """Stop the motion first, then the connections, then the drives and the bus."""
        try:
            self._stop_active_run()
        finally:
            self._abandon_preparing("the daemon is shutting down")
            try:
                self.server.close()
            finally:
                if self.rig is not None:
                    self.rig.close()
                    self.rig = None
        log.info("daemon stopped", extra={"event": "stopped"})

    def _stop_active_run(self) -> None:
        """Bring a run in progress to rest and let its session end (log finished).

        Whatever ends the service (a signal, a bug in the loop), the bus is never closed
        under a moving robot: a stop request first, a quick stop if the run does not end
        within :data:`STOP_WAIT_S`.
        """
        run = self.active
        if run is None:
            return
        if not run.stop.requested:
            run.stop.request(self.shutdown.reason or "daemon teardown")
        forwarded = self.shutdown.count
        deadline = time.monotonic() + STOP_WAIT_S
        urgent = False
        while run.thread.is_alive():
            run.thread.join(0.1)
            now = time.monotonic()
            if self.shutdown.count > forwarded and not urgent:
                forwarded = self.shutdown.count
                run.stop.request(self.shutdown.reason or "shutdown")  # a second: quick stop
                urgent = True
            if now >= deadline:
                if urgent:
                    log.error("the run did not end after a quick stop: closing the drives")
                    break
                log.error("the run did not come to rest in %.0f s: quick stop", STOP_WAIT_S)
                run.stop.request("teardown time-out")
                urgent = True
                deadline = now + STOP_WAIT_S
        self._reap_run()

    # -- main loop -----------------------------------------------------------------------------

    def _loop(self) -> None:
        wd = watchdog_interval(self.settings)
        next_wd = time.monotonic()
        next_check = time.monotonic()
        forwarded = 0
        while True:
            if self.shutdown.requested:
                self._abandon_preparing("the daemon is shutting down")
                if self.active is None:
                    return
                # forward every signal to the run: the first stops smoothly, a second quick-stops
                while forwarded < self.shutdown.count:
                    self.active.stop.request(self.shutdown.reason or "shutdown")
                    forwarded += 1
            # poll a run's checks often; otherwise wake for the idle check
            timeout = 0.02 if self.preparing is not None else self.settings.idle_check_s
            self.server.poll(timeout)
            self._finish_preparing()
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

    # -- requests ------------------------------------------------------------------------------

    def handle_line(self, line: bytes) -> dict[str, Any]:
        """The reply to one request line (never raises; a ``run`` waits for its checks)."""
        reply = self._handle(None, line)
        if reply is not None:
            return reply
        assert self.preparing is not None
        self.preparing.job.wait(3600.0)
        return self._finish_preparing() or {"ok": False, "error": "the run was abandoned"}

    def _handle(self, client: Client | None, line: bytes) -> dict[str, Any] | None:
        """The reply to one request line, or None when a ``run`` replies after its checks."""
        try:
            req = parse_request(line)
            cmd = req.get("cmd")
            if cmd == "status":
                _only(req, {"cmd"})
                return {"ok": True, **self.status()}
            if cmd == "run":
                _only(req, {"cmd", "trajectory", "label", "payload"})
                self.start_run(req, client)
                return None
            if cmd == "stop":
                _only(req, {"cmd"})
                return {"ok": True, **self.stop_run()}
            raise RequestError(
                f"malformed request: unknown cmd {cmd!r} (expected status, run or stop)"
            )
        except Exception as exc:
            return _error_reply(exc)

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
        if self.active is not None:
            state = "running"
        elif self.preparing is not None:
            state = "preparing"
        else:
            state = "fault" if self.fault else "idle"
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

    def start_run(self, req: dict[str, Any], client: Client | None = None) -> None:
        """Check the request's fields and start its checks on a worker (the ``run`` request).

        The reply is sent when the checks are over (:meth:`_finish_preparing`).

        Raises
        ------
        RequestError
            A run is prepared or in progress, the daemon is shutting down, or a field is bad.
        """
        if self.active is not None:
            raise RequestError(
                f"a run is already in progress ({self.active.session.prepared.label}): "
                "send stop or wait"
            )
        if self.preparing is not None:
            raise RequestError(f"a run is being prepared ({self.preparing.label}): wait")
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
        job = PrepareJob(
            self.cfg, RunRequest(trajectory=trajectory, out=out, label=label, payload=payload)
        )
        self.preparing = _Preparing(job=job, client=client, label=name)

    def _finish_preparing(self) -> dict[str, Any] | None:
        """Once a run's checks are over: boot if needed, plan, start the run, send the reply."""
        prep = self.preparing
        if prep is None or not prep.job.done:
            return None
        self.preparing = None
        try:
            reply = {"ok": True, **self._start_checked(prep)}
        except Exception as exc:
            reply = _error_reply(exc)
        if prep.client is not None:
            self.server.reply(prep.client, reply)
        return reply

    def _start_checked(self, prep: _Preparing) -> dict[str, Any]:
        prepared = prep.job.result()
        out = prepared.request.out
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
        session.plan()  # bounded: one period of the excitation besides approach and retreat
        run = _ActiveRun(session=session, thread=threading.Thread(), stop=stop, out=out)

        def target() -> None:
            try:  # the trace ([acquisition] can_trace) opens a bus handle of its own per run
                with can_trace(self.cfg.bus, prepared.request.can_trace):
                    run.outcome.update(run_session(session))
            except BaseException as exc:  # the trace could not be opened: the run never began
                run.outcome.setdefault("error", exc)

        run.thread = threading.Thread(target=target, name="drivegain-cycle", daemon=True)
        self.active = run
        self.fault = None
        run.thread.start()
        log.info(
            "run started",
            extra={"event": "run", "label": prepared.label, "out": str(out)},
        )
        return {"label": prepared.label, "out": str(out), "duration_s": session.duration_s}

    def _abandon_preparing(self, why: str) -> None:
        prep = self.preparing
        if prep is None:
            return
        self.preparing = None  # the worker only reads files: it ends by itself, unused
        log.info("run checks abandoned: %s", why, extra={"event": "abandoned"})
        if prep.client is not None:
            self.server.reply(prep.client, {"ok": False, "error": why})

    def stop_run(self) -> dict[str, Any]:
        """Ask the run in progress to come to rest (the ``stop`` request)."""
        if self.active is None:
            if self.preparing is not None:
                label = self.preparing.label
                self._abandon_preparing("stopped by a stop request before the run started")
                return {"stopping": label}
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
        if err is not None:
            # a log that could not even be started would block nothing but clutter the folder
            discard_unrecorded(run.out)
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
        elif self.preparing is not None:
            text = f"preparing {self.preparing.label}"
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


def _error_reply(exc: BaseException) -> dict[str, Any]:
    """The ``{"ok": false}`` reply of a refused or failed request (logged here)."""
    if isinstance(exc, InputError):
        log.warning("request refused: %s", exc, extra={"event": "refused"})
        return {"ok": False, "error": str(exc)}
    if isinstance(exc, DrivegainError):
        log.error("request failed: %s", exc, extra={"event": "error"})
        return {"ok": False, "error": str(exc)}
    # a bug must not take the service down
    log.error("internal error serving a request", exc_info=exc)
    return {"ok": False, "error": f"internal error: {type(exc).__name__}: {exc}"}


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
