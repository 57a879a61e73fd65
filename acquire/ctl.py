"""``drivegain ctl status|run|stop``: the daemon's client, so nobody writes JSON into a socket.

The socket is ``--socket``, else the ``[daemon] socket`` of ``--config`` (read as the daemon reads
it: a relative path is relative to the working directory). Each action sends one request of the
protocol of :mod:`.daemon` and prints a summary of the reply, or the reply itself with ``--json``.

Exit status: 0 when the daemon replied ok (``run --wait``: and the run did not end with a fault),
1 when it answered with an error, 2 for bad input (no socket, not a socket, permission denied,
nobody listening: one line naming the path).
"""

from __future__ import annotations

import argparse
import errno
import json
import socket
import stat
import time
from pathlib import Path
from typing import Any

from drivegain.acquire.control import read_reply
from drivegain.errors import DrivegainError, InputError

#: How long a reply may take, s: a ``run`` replies once its checks passed and its motion is
#: planned (files read, limits checked), the others at once.
REPLY_TIMEOUT_S = {"run": 120.0, "status": 10.0, "stop": 10.0}
#: Period of the status requests of ``run --wait``, s.
WAIT_POLL_S = 0.2


class DaemonError(DrivegainError):
    """The daemon answered a request with ``{"ok": false, "error": ...}``."""


def socket_path(sock: Path | None, config: Path | None) -> Path:
    """The daemon's control socket: ``sock``, else the ``[daemon] socket`` of ``config``.

    Parameters
    ----------
    sock
        ``--socket``, if given.
    config
        ``--config``, the acquisition TOML the daemon was started with, if given.

    Raises
    ------
    InputError
        Neither is given, or the TOML has no ``[daemon]`` table (one line naming the file).
    """
    if sock is not None:
        return sock
    if config is None:
        raise InputError(
            "no daemon socket: give --socket PATH, or --config ACQ.toml with a [daemon] socket"
        )
    from drivegain.acquire.config import DaemonSettings
    from drivegain.config._toml import read_root
    from drivegain.config.schema import load_table
    from drivegain.errors import ConfigError

    root = read_root(config, {"acquisition", "bus", "simulation", "daemon"})
    if not root.has("daemon"):
        raise ConfigError("no [daemon] table: give --socket PATH", file=config)
    return load_table(DaemonSettings, root.table("daemon")).socket


def send(path: Path, message: dict[str, Any], timeout: float = 10.0) -> dict[str, Any]:
    """Send one request to the daemon listening on ``path`` and return its reply.

    Parameters
    ----------
    path
        The control socket.
    message
        The request (one JSON object).
    timeout
        Longest wait for the connection and for the reply, s.

    Raises
    ------
    InputError
        ``path`` is missing, not a socket, not ours or nobody listens on it (one line naming it).
    DrivegainError
        The daemon closed the connection or did not reply within ``timeout``.
    """
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise InputError(f"{path}: no such socket (is the daemon running?)") from None
    except PermissionError:
        raise InputError(f"{path}: permission denied") from None
    except OSError as exc:
        raise InputError(f"{path}: {exc.strerror or exc}") from None
    if not stat.S_ISSOCK(mode):
        raise InputError(f"{path}: not a socket")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        try:
            s.connect(str(path))
        except PermissionError:
            raise InputError(f"{path}: permission denied") from None
        except ConnectionRefusedError:
            raise InputError(f"{path}: nobody listens on it (is the daemon running?)") from None
        except OSError as exc:
            if exc.errno == errno.ENAMETOOLONG or "too long" in str(exc):
                raise InputError(f"{path}: path too long for a Unix socket") from None
            raise InputError(f"{path}: {exc.strerror or exc}") from None
        try:
            s.sendall((json.dumps(message) + "\n").encode())
            reply = read_reply(s)
        except TimeoutError:
            raise DrivegainError(f"{path}: no reply from the daemon within {timeout:g} s") from None
        except (ConnectionError, ValueError) as exc:
            raise DrivegainError(f"{path}: {exc}") from None
    if reply.get("ok") is False and reply.get("error") == "permission denied":
        raise InputError(f"{path}: permission denied (the daemon runs as another user)")
    return reply


def run_request(
    trajectory: Path, payload: Path | None = None, label: str | None = None
) -> dict[str, Any]:
    """The ``run`` request: paths made absolute (the daemon's working directory is not ours)."""
    return {
        "cmd": "run",
        "trajectory": str(trajectory.absolute()),
        "payload": None if payload is None else str(payload.absolute()),
        "label": label,
    }


def wait_for_run(path: Path, out: str) -> dict[str, Any]:
    """Poll ``status`` until the run writing ``out`` has ended; the daemon's ``last_run``."""
    while True:
        status = send(path, {"cmd": "status"})
        if not status.get("ok"):
            raise DaemonError(str(status.get("error")))
        run = status.get("run")
        if run is None or run.get("out") != out:
            last: dict[str, Any] = status.get("last_run") or {}
            return last
        time.sleep(WAIT_POLL_S)


def status_summary(reply: dict[str, Any]) -> str:
    """Lines of a ``status`` reply for a person."""
    lines = [
        f"{reply.get('state')}: {reply.get('runs')} runs since start (pid {reply.get('pid')}, "
        f"drivegain {reply.get('version')}, {reply.get('clock')} clock, period "
        f"{_ms(reply.get('period_s'))})"
    ]
    run = reply.get("run")
    if run:
        lines.append(
            f"run {run['label']}: {run['state']} t={run['t']:.1f}/{run['duration_s']:.1f} s, "
            f"cycle {run['cycle']} -> {run['out']}"
        )
    if reply.get("fault"):
        lines.append(f"fault: {reply['fault']}")
    last = reply.get("last_run")
    if last:
        lines.append(f"last run: {run_summary(last)}")
    return "\n".join(lines)


def run_summary(last: dict[str, Any]) -> str:
    """One line of a finished run (the daemon's ``last_run``)."""
    text = f"{last.get('label')} {last.get('state')}, {last.get('cycles')} cycles"
    if last.get("out"):
        text += f" -> {last['out']}"
    if last.get("stop_reason"):
        text += f" (stopped: {last['stop_reason']})"
    if last.get("fault"):
        text += f" (fault: {last['fault']})"
    return text


def _ms(period_s: Any) -> str:
    return f"{period_s * 1e3:g} ms" if isinstance(period_s, int | float) else "?"


def ctl_command(args: argparse.Namespace) -> int:
    """``drivegain ctl status|run|stop``: one request to the daemon, its reply summarised.

    Returns
    -------
    int
        0 when the reply is ok (``run --wait``: and the run ended without a fault), 1 when the
        daemon answered with an error. Bad input raises :class:`InputError` (exit status 2).
    """
    action: str = args.ctl_action
    path = socket_path(args.socket, args.config)
    if action == "run":
        message = run_request(args.trajectory, args.payload, args.label)
    else:
        message = {"cmd": action}
    reply = send(path, message, REPLY_TIMEOUT_S[action])
    if not reply.get("ok"):
        if args.json:
            print(json.dumps(reply))
            return 1
        raise DaemonError(str(reply.get("error")))
    last: dict[str, Any] | None = None
    if action == "run" and args.wait:
        last = wait_for_run(path, str(reply.get("out")))
    if args.json:
        print(json.dumps(reply if last is None else {**reply, "last_run": last}))
    elif action == "status":
        print(status_summary(reply))
    elif action == "run":
        print(
            f"started {reply.get('label')} ({reply.get('duration_s', 0):.1f} s) -> {reply['out']}"
        )
        if last is not None:
            print(run_summary(last))
    else:
        print(f"stopping {reply.get('stopping')}")
    if last is not None and last.get("state") == "fault":
        if args.json:
            return 1
        raise DaemonError(f"the run ended with a fault: {last.get('fault')}")
    return 0
