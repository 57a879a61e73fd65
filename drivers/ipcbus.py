"""A python-can bus between processes of one machine: CAN frames over a Unix socket.

The ``virtual`` interface only connects buses of one process. The realtime simulation runs the
simulated drives in a child process (as real drives are separate devices, they then take no CPU
time or interpreter lock from the master); this interface connects the two. It is registered
with python-can as the ``drivegain-ipc`` interface (entry point in pyproject.toml), so the master
opens it like any other: ``can.Bus(interface="drivegain-ipc", channel=SOCKET_PATH)``.

Topology: one ``server`` bus (the simulated cell) creates the socket; ``client`` buses connect to
it. A frame sent by the server reaches every client; a frame sent by a client reaches the server
and every other client: every bus sees every other bus's frames, as on a CAN bus, and never its
own (no ``receive_own_messages``). Like ``virtual`` it has no bitrate, arbitration or loss;
frames keep their order per sender. Frames are packed with :data:`FRAME` (one seqpacket each).
A received frame's timestamp is the sender's ``time.time()`` when it sent it, as on the virtual
bus: the instant a frame is on the wire, which a CAN interface stamps in hardware, not when a
busy reader thread gets round to it.

A bus that does not read loses frames, as a CAN controller whose receive buffer overflows: sends
never block (a full socket buffer drops the frame for that receiver and counts it in
``overflows``), so one stuck reader cannot stall the others. A closed peer ends a client: its next
``recv`` raises :class:`can.CanOperationError` (the master's reader then reports a bus error); a
server simply forgets a client that left.
"""

from __future__ import annotations

import os
import select
import socket
import struct
import threading
import time
import weakref
from pathlib import Path
from typing import Any

import can

from drivegain.unixsock import NotASocket, SocketInUse, bind_private

#: python-can interface name of this bus.
INTERFACE = "drivegain-ipc"
#: Wire format of one frame: send time (s since the epoch), arbitration id, flags, DLC, 8 bytes.
FRAME = struct.Struct("<dIBB8s")
_EXTENDED, _REMOTE, _ERROR = 1, 2, 4
#: How long a client retries connecting to a server that is not listening yet, s.
CONNECT_TIMEOUT_S = 5.0
#: Socket send buffer, bytes: some thousands of frames before a receiver overflows.
SEND_BUFFER = 1 << 20
_ROLES = ("client", "server")
#: Buses not shut down yet (the test suite's leak check reads it).
OPEN_BUSES: weakref.WeakSet[IpcBus] = weakref.WeakSet()


def _pack(msg: can.Message) -> bytes:
    flags = (
        (_EXTENDED if msg.is_extended_id else 0)
        | (_REMOTE if msg.is_remote_frame else 0)
        | (_ERROR if msg.is_error_frame else 0)
    )
    return FRAME.pack(time.time(), msg.arbitration_id, flags, msg.dlc, bytes(msg.data))


def _unpack(frame: bytes, channel: str) -> can.Message:
    sent, can_id, flags, dlc, data = FRAME.unpack(frame)
    return can.Message(
        timestamp=sent,
        arbitration_id=can_id,
        is_extended_id=bool(flags & _EXTENDED),
        is_remote_frame=bool(flags & _REMOTE),
        is_error_frame=bool(flags & _ERROR),
        dlc=dlc,
        data=data[:dlc] if not flags & _REMOTE else None,
        channel=channel,
        is_rx=True,
    )


class IpcBus(can.BusABC):
    """CAN frames between processes over a Unix seqpacket socket.

    Parameters
    ----------
    channel
        Path of the socket file.
    role
        ``server`` creates the socket (mode 0600; a socket file left by a killed server is
        replaced, a live server's or any other existing file is an error), ``client`` connects
        to it, retrying for ``connect_timeout_s``.
    connect_timeout_s
        Client only: how long to wait for the server, s.
    kwargs
        Passed to :class:`can.BusABC` (``can_filters``; ``bitrate`` is accepted and ignored).

    Raises
    ------
    can.CanInitializationError
        Bad role, the path is taken by something else, or no server answered in time.
    """

    def __init__(
        self,
        channel: str | os.PathLike[str],
        role: str = "client",
        connect_timeout_s: float = CONNECT_TIMEOUT_S,
        **kwargs: Any,
    ) -> None:
        if role not in _ROLES:
            raise can.CanInitializationError(f"role must be one of {_ROLES}, got {role!r}")
        kwargs.pop("bitrate", None)
        kwargs.pop("receive_own_messages", None)
        super().__init__(channel=str(channel), **kwargs)
        self.path = Path(channel)
        self.role = role
        self.channel_info = f"drivegain IPC bus {self.path} ({role})"
        self._peers: list[socket.socket] = []
        self._peers_lock = threading.Lock()
        self._listener: socket.socket | None = None
        self._open = True
        #: Frames dropped because a receiver's buffer was full.
        self.overflows = 0
        if role == "server":
            self._listener = self._listen()
        else:
            self._peers.append(self._connect(connect_timeout_s))
        OPEN_BUSES.add(self)

    # --- set-up ---------------------------------------------------------------------------------
    def _listen(self) -> socket.socket:
        try:
            sock = bind_private(self.path, socket.SOCK_SEQPACKET, backlog=8)
        except (NotASocket, SocketInUse) as exc:
            raise can.CanInitializationError(str(exc)) from None
        except OSError as exc:
            raise can.CanInitializationError(f"cannot listen on {self.path}: {exc}") from None
        return sock

    def _connect(self, timeout_s: float) -> socket.socket:
        deadline = time.monotonic() + timeout_s
        while True:
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            try:
                sock.connect(str(self.path))
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
                return sock
            except (FileNotFoundError, ConnectionRefusedError) as exc:
                sock.close()
                if time.monotonic() >= deadline:
                    raise can.CanInitializationError(
                        f"no drivegain IPC bus server at {self.path} after {timeout_s:g} s: {exc}"
                    ) from None
                time.sleep(0.02)
            except OSError as exc:
                sock.close()
                raise can.CanInitializationError(f"cannot connect to {self.path}: {exc}") from None

    # --- python-can interface -------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` to every other bus on the socket."""
        if not self._open:
            raise can.CanOperationError("Cannot operate on a closed bus")
        self._broadcast(_pack(msg), None)

    def _broadcast(self, frame: bytes, source: socket.socket | None) -> None:
        with self._peers_lock:
            peers = list(self._peers)
        for peer in peers:
            if peer is source:
                continue
            try:
                peer.send(frame, socket.MSG_DONTWAIT)
            except BlockingIOError:
                self.overflows += 1  # that receiver is not reading: its frame is lost
            except OSError as exc:
                if self.role == "client":
                    raise can.CanOperationError(f"{self.path}: send failed: {exc}") from None
                self._drop(peer)  # a client that left

    def _drop(self, peer: socket.socket) -> None:
        with self._peers_lock:
            if peer in self._peers:
                self._peers.remove(peer)
        peer.close()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._open:
            raise can.CanOperationError("Cannot operate on a closed bus")
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            with self._peers_lock:
                watched = list(self._peers)
            if self._listener is not None:
                watched.append(self._listener)
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                ready, _, _ = select.select(watched, [], [], wait)
            except (OSError, ValueError):  # a socket closed by shutdown() meanwhile
                if not self._open:
                    raise can.CanOperationError("Cannot operate on a closed bus") from None
                continue
            for sock in ready:
                if sock is self._listener:
                    peer, _ = sock.accept()
                    peer.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
                    with self._peers_lock:
                        self._peers.append(peer)
                    continue
                try:
                    frame = sock.recv(FRAME.size)
                except OSError:
                    frame = b""
                if not frame:
                    if self.role == "client":
                        self._open = False
                        raise can.CanOperationError(f"{self.path}: the bus server went away")
                    self._drop(sock)
                    continue
                if self.role == "server" and len(self._peers) > 1:
                    self._broadcast(frame, sock)  # clients see each other, as on a bus
                return _unpack(frame, str(self.path)), False
            if not ready and deadline is not None and time.monotonic() >= deadline:
                return None, False

    def shutdown(self) -> None:
        """Close every connection; a server removes its socket file."""
        super().shutdown()
        OPEN_BUSES.discard(self)
        if not self._open and not self._peers and self._listener is None:
            return
        self._open = False
        with self._peers_lock:
            peers, self._peers = self._peers, []
        for peer in peers:
            peer.close()
        if self._listener is not None:
            self._listener.close()
            self._listener = None
            try:
                self.path.unlink()
            except FileNotFoundError:
                pass
