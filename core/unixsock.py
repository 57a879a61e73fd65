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


def bind_private(path: Path, kind: int) -> socket.socket:
    """A Unix socket of type ``kind`` (``SOCK_STREAM``, ``SOCK_SEQPACKET``) bound at ``path``.

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
    old = os.umask(0o177)
    try:
        sock.bind(str(path))
        os.chmod(path, 0o600)
    except OSError:
        sock.close()
        raise
    finally:
        os.umask(old)
    return sock
