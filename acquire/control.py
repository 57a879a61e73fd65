"""The daemon's control connections: accept, read JSON lines, write replies, within limits.

A hardware-facing service must not be knocked over by its clients, so every resource a client
can make the daemon spend is bounded:

- accept errors (out of file descriptors, ``EMFILE``; out of kernel memory) are logged, accepting
  pauses for :data:`ACCEPT_BACKOFF_S` and the service goes on;
- at most ``max_clients`` connections at once (less when the descriptor limit leaves no room for
  them beside :data:`FD_RESERVE` kept for runs); one more is told so in one JSON line and closed;
- a connection that sends nothing for ``client_idle_s`` is closed;
- a request line is at most :data:`MAX_LINE` bytes; replies waiting for a client that does not
  read them are at most ``client_buffer_bytes``: past that the client is dropped.

The socket is created with permissions 0600 (owner only) and a peer of another user is refused.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import resource
import selectors
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivegain.acquire.config import DaemonSettings
from drivegain.errors import ConfigError, InputError
from drivegain.unixsock import NotASocket, SocketInUse, bind_private

log = logging.getLogger(__name__)

#: Longest request line, bytes.
MAX_LINE = 64 * 1024
#: Pause of accepting after an accept error, s: long enough not to spin on a listener that
#: stays readable, short enough that clients barely notice once descriptors are free again.
ACCEPT_BACKOFF_S = 0.2
#: Most connections taken from the backlog in one step of the loop.
ACCEPT_BURST = 32
#: File descriptors kept free for runs (log file, folder fsync, files read by a run request,
#: a new bus after a fault) when the connection limit is derived from ``RLIMIT_NOFILE``.
FD_RESERVE = 16
#: Deepest nesting of a request line's JSON (a request is a flat object).
MAX_DEPTH = 32
#: Errors of ``accept`` that say the process or the system is short of a resource.
_RESOURCE_ERRNOS = {errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM}


class RequestError(InputError):
    """A control request that cannot be served (the reply carries the message)."""


@dataclass
class Client:
    """One control connection: the bytes read and not yet handled, the replies not yet sent.

    ``waiting`` is set while a request of this client is being served off the main loop (a
    ``run`` under its checks): its later lines wait, so replies keep the order of requests.
    """

    sock: socket.socket
    fd: int
    buffer: bytearray = field(default_factory=bytearray)
    out: bytearray = field(default_factory=bytearray)
    closing: bool = False
    waiting: bool = False
    last_active: float = field(default_factory=time.monotonic)


#: What a request handler returns: the reply, or ``None`` when it will come later
#: (:meth:`ControlServer.reply`).
Handler = Callable[[Client, bytes], dict[str, Any] | None]


class ControlServer:
    """The listening socket and its connections (used from one thread, the daemon's loop).

    Parameters
    ----------
    settings
        The ``[daemon]`` table (socket path, limits).
    handle
        Called with each complete request line; returns the reply or ``None`` (deferred).
    source
        The acquisition TOML (named in configuration errors).
    """

    def __init__(self, settings: DaemonSettings, handle: Handler, source: Path):
        self.settings = settings
        self.handle = handle
        self.source = source
        self.max_clients = settings.max_clients
        self.clients: dict[int, Client] = {}
        self.refused = 0
        self.dropped = 0
        self.accept_errors = 0
        self._selector = selectors.DefaultSelector()
        self._listener: socket.socket | None = None
        self._resume_accept_at: float | None = None
        self._accept_failing = False
        self._at_limit = False
        self._uid = os.getuid()

    # -- lifecycle -----------------------------------------------------------------------------

    def listen(self) -> None:
        """Bind the private socket and listen.

        Raises
        ------
        ConfigError
            The path is taken by another file or by a live daemon.
        """
        path = self.settings.socket
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        try:
            listener = bind_private(path, socket.SOCK_STREAM, backlog=16)
        except NotASocket:
            raise ConfigError(
                f"{path} exists and is not a socket", file=self.source, key="daemon.socket"
            ) from None
        except SocketInUse:
            raise ConfigError(
                f"another daemon is listening on {path}", file=self.source, key="daemon.socket"
            ) from None
        listener.setblocking(False)
        self._selector.register(listener, selectors.EVENT_READ, None)
        self._listener = listener
        self.max_clients = _client_budget(self.settings.max_clients)

    def close(self) -> None:
        """Close every connection and the listener, remove the socket file."""
        for client in list(self.clients.values()):
            self.close_client(client)
        if self._listener is not None:
            self._unregister_listener()
            self._listener.close()
            self._listener = None
            try:
                self.settings.socket.unlink()
            except OSError:
                pass
        self._selector.close()

    # -- the loop's step -----------------------------------------------------------------------

    def poll(self, timeout: float) -> None:
        """Wait up to ``timeout`` s for socket events and serve them; enforce the time-outs."""
        now = time.monotonic()
        if self._resume_accept_at is not None:
            if now >= self._resume_accept_at:
                self._resume_accept_at = None
                if self._listener is not None:
                    self._selector.register(self._listener, selectors.EVENT_READ, None)
            else:
                timeout = min(timeout, self._resume_accept_at - now)
        for key, mask in self._selector.select(max(timeout, 0.0)):
            if key.data is None:
                # a burst of connections is taken in one go (bounded: the loop has other work)
                for _ in range(ACCEPT_BURST):
                    if not self._accept():
                        break
            else:
                self._service(key.data, mask)
        self._expire_idle(time.monotonic())

    def reply(self, client: Client, obj: dict[str, Any]) -> None:
        """Send a deferred reply, then serve the lines the client sent meanwhile."""
        if self.clients.get(client.fd) is not client:
            return  # the client went away while its request was served
        client.waiting = False
        client.last_active = time.monotonic()
        if self._queue_reply(client, obj):
            self._handle_lines(client)
            self._flush(client)

    # -- accepting -----------------------------------------------------------------------------

    def _accept(self) -> bool:
        """Take one pending connection; False when there was none or accepting failed."""
        if self._listener is None or self._resume_accept_at is not None:
            return False
        try:
            sock, _ = self._listener.accept()
        except (BlockingIOError, InterruptedError, ConnectionAbortedError):
            return False
        except OSError as exc:
            # EMFILE & co: the pending connection stays in the backlog; stop watching the
            # listener for a moment (it would stay readable and spin the loop), then go on
            self.accept_errors += 1
            level = logging.WARNING if exc.errno in _RESOURCE_ERRNOS else logging.ERROR
            if self._accept_failing:
                level = logging.DEBUG  # said once per episode, not five times a second
            self._accept_failing = True
            log.log(
                level,
                "cannot accept a control connection (%s): pausing %.1f s",
                exc.strerror or exc,
                ACCEPT_BACKOFF_S,
                extra={"event": "accept_error", "errno": exc.errno},
            )
            self._unregister_listener()
            self._resume_accept_at = time.monotonic() + ACCEPT_BACKOFF_S
            return False
        if self._accept_failing:
            self._accept_failing = False
            log.info("accepting control connections again", extra={"event": "accept_ok"})
        uid = _peer_uid(sock)
        if uid is not None and uid not in (self._uid, 0):
            log.warning(
                "refused a connection from uid %d", uid, extra={"event": "refused", "uid": uid}
            )
            _send_and_close(sock, {"ok": False, "error": "permission denied"})
            return True
        if len(self.clients) >= self.max_clients:
            self.refused += 1
            # once per episode at full limit: a client connecting in a loop floods no journal
            level = logging.DEBUG if self._at_limit else logging.WARNING
            self._at_limit = True
            log.log(
                level,
                "refused a control connection: %d open (the limit)",
                len(self.clients),
                extra={"event": "refused", "clients": len(self.clients)},
            )
            _send_and_close(
                sock,
                {
                    "ok": False,
                    "error": f"too many connections ({self.max_clients} open, the limit): "
                    "close one and retry",
                },
            )
            return True
        self._at_limit = False
        sock.setblocking(False)
        client = Client(sock, sock.fileno())
        self.clients[client.fd] = client
        self._selector.register(sock, selectors.EVENT_READ, client)
        return True

    def _unregister_listener(self) -> None:
        try:
            self._selector.unregister(self._listener)  # type: ignore[arg-type]
        except (KeyError, ValueError):
            pass

    # -- serving -------------------------------------------------------------------------------

    def _service(self, client: Client, mask: int) -> None:
        if mask & selectors.EVENT_READ:
            try:
                data: bytes | None = client.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                data = None
            except OSError:
                data = b""
            if data == b"":
                self.close_client(client)
                return
            if data:
                client.last_active = time.monotonic()
                client.buffer.extend(data)
                if not self._handle_lines(client):
                    return
        self._flush(client)

    def _handle_lines(self, client: Client) -> bool:
        """Serve the complete lines buffered; False when the client was dropped."""
        start = 0
        buf = client.buffer
        while not client.waiting and not client.closing:
            end = buf.find(b"\n", start)
            if end < 0:
                break
            line = bytes(buf[start:end])
            start = end + 1
            reply = self.handle(client, line)
            if reply is None:
                client.waiting = True  # deferred: the reply comes through reply()
            elif not self._queue_reply(client, reply):
                return False
        del buf[:start]  # once per read, not once per line
        if len(buf) > MAX_LINE:
            buf.clear()
            error = (
                f"more than {MAX_LINE} bytes of requests while a run request is checked"
                if client.waiting
                else f"request longer than {MAX_LINE} bytes"
            )
            if not self._queue_reply(client, {"ok": False, "error": error}):
                return False
            client.closing = True
        return True

    def _queue_reply(self, client: Client, obj: dict[str, Any]) -> bool:
        """Append a reply; drop a client whose unsent replies pass the limit. Still open?"""
        client.out.extend(_encode(obj))
        limit = self.settings.client_buffer_bytes
        if len(client.out) > limit:
            self._send(client)  # a reader may just be behind: give it what the kernel takes
            if client.fd not in self.clients:
                return False
            if len(client.out) > limit:
                self.dropped += 1
                log.warning(
                    "dropped a control connection that does not read its replies "
                    "(%d bytes waiting, limit %d)",
                    len(client.out),
                    limit,
                    extra={"event": "dropped"},
                )
                self.close_client(client)
                return False
        return True

    def _send(self, client: Client) -> None:
        if not client.out:
            return
        try:
            sent = client.sock.send(client.out)
            del client.out[:sent]
        except (BlockingIOError, InterruptedError):
            pass
        except OSError:
            self.close_client(client)

    def _flush(self, client: Client) -> None:
        self._send(client)
        if client.fd not in self.clients:
            return
        if client.closing and not client.out:
            self.close_client(client)
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.out else 0)
        self._selector.modify(client.sock, events, client)

    def _expire_idle(self, now: float) -> None:
        limit = self.settings.client_idle_s
        for client in list(self.clients.values()):
            if client.waiting or now - client.last_active <= limit:
                continue
            log.info(
                "closed a control connection idle for %.0f s",
                now - client.last_active,
                extra={"event": "idle_timeout"},
            )
            error = f"idle for more than {limit:g} s: connection closed"
            client.out.extend(_encode({"ok": False, "error": error}))
            self._send(client)  # best effort: a client that does not read misses it
            self.close_client(client)

    def close_client(self, client: Client) -> None:
        """Forget and close one connection."""
        if self.clients.get(client.fd) is client:
            del self.clients[client.fd]
        try:
            self._selector.unregister(client.sock)
        except (KeyError, ValueError):
            pass
        client.sock.close()


def parse_request(line: bytes) -> dict[str, Any]:
    """A request line as a JSON object.

    Raises
    ------
    RequestError
        Not UTF-8, not JSON, nested deeper than :data:`MAX_DEPTH`, or not an object.
    """
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RequestError(f"malformed request: not a JSON line ({exc})") from None
    if _depth(text) > MAX_DEPTH:
        raise RequestError(f"malformed request: nested deeper than {MAX_DEPTH} levels")
    try:
        req = json.loads(text)
    except RecursionError:  # the depth bound above makes this unreachable; kept as a net
        raise RequestError(f"malformed request: nested deeper than {MAX_DEPTH} levels") from None
    except ValueError as exc:
        raise RequestError(f"malformed request: not a JSON line ({exc})") from None
    if not isinstance(req, dict):
        raise RequestError("malformed request: expected a JSON object")
    return req


def _depth(text: str) -> int:
    """An upper bound of the nesting depth of a JSON text (brackets inside strings count too,
    which only makes it stricter), in one linear pass without recursion."""
    if text.count("[") + text.count("{") <= MAX_DEPTH:
        return 0  # the common case, without a loop in Python
    depth = deepest = 0
    for ch in text:
        if ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def _client_budget(configured: int) -> int:
    """``configured``, lowered so that the connections fit under ``RLIMIT_NOFILE`` with
    :data:`FD_RESERVE` descriptors to spare beside those already open."""
    try:
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        in_use = len(os.listdir("/proc/self/fd"))
    except (OSError, ValueError):
        return configured
    if soft == resource.RLIM_INFINITY:
        return configured
    room = soft - in_use - FD_RESERVE
    if room < configured:
        budget = max(1, room)
        log.warning(
            "max_clients %d lowered to %d: the file descriptor limit is %d (%d open, %d kept "
            "for runs); raise LimitNOFILE",
            configured,
            budget,
            soft,
            in_use,
            FD_RESERVE,
            extra={"event": "limit", "max_clients": budget},
        )
        return budget
    return configured


def _send_and_close(sock: socket.socket, obj: dict[str, Any]) -> None:
    try:
        sock.setblocking(False)
        sock.send(_encode(obj))  # one short line: fits any socket buffer, never blocks
    except OSError:
        pass
    sock.close()


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
