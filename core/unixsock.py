"""Private Unix sockets for local servers (the daemon's control socket, the simulated drives' bus).

A server takes its path over only from a server that died: a socket file nobody answers on is
replaced, a live one or any other file is refused. The socket is created with mode 0600 (under a
umask, so there is no moment when another user could connect).
"""

from __future__ import annotations

import os
import socket
import stat
from pathlib import Path


class NotASocket(FileExistsError):
    """The path exists and is not a socket (left alone)."""


class SocketInUse(FileExistsError):
    """A server is listening on the path."""


def bind_private(path: Path, kind: int, backlog: int = 16) -> socket.socket:
    """A listening Unix socket of type ``kind`` (``SOCK_STREAM``, ``SOCK_SEQPACKET``) at ``path``.

    The socket is bound under a temporary name beside ``path``, set listening, then renamed
    into place: a client that sees the file can connect at once (a socket bound but not yet
    listening refuses connections, which a client waiting for the file would take as an error).

    Raises
    ------
    NotASocket, SocketInUse
        The path is taken (see the module docstring).
    OSError
        The socket cannot be bound (missing directory, permissions, path too long).
    """
    try:
        st = path.lstat()
    except FileNotFoundError:
        pass
    else:
        if not stat.S_ISSOCK(st.st_mode):
            raise NotASocket(f"{path} exists and is not a socket")
        probe = socket.socket(socket.AF_UNIX, kind)
        try:
            probe.connect(str(path))
        except OSError:
            path.unlink()  # left by a server that died
        else:
            raise SocketInUse(f"a server is listening on {path}")
        finally:
            probe.close()
    sock = socket.socket(socket.AF_UNIX, kind)
    # A short name: the staging path must fit the same 108-byte limit as ``path``.
    staging = path.with_name(f".{os.getpid():x}")
    old = os.umask(0o177)
    try:
        staging.unlink(missing_ok=True)
        sock.bind(str(staging))
        os.chmod(staging, 0o600)
        sock.listen(backlog)
        os.replace(staging, path)
    except OSError:
        sock.close()
        staging.unlink(missing_ok=True)
        raise
    finally:
        os.umask(old)
    return sock
