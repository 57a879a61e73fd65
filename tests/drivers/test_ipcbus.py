"""The cross-process bus (``drivegain-ipc``): frames, topology, failures, through python-can."""

from __future__ import annotations

import os
import socket
import stat
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

import can
import pytest

from drivegain.drivers.bus import BusConfig, open_bus
from drivegain.drivers.ipcbus import INTERFACE, IpcBus
from drivegain.errors import BusError


@pytest.fixture
def path() -> Iterator[Path]:
    # Unix socket paths are limited to ~100 bytes: pytest's tmp_path can be longer.
    d = Path(f"/tmp/dg-ipc-{os.getpid()}-{time.monotonic_ns()}")
    d.mkdir()
    yield d / "bus.sock"
    for f in d.iterdir():
        f.unlink()
    d.rmdir()


def _bus(path: Path, role: str = "client", **kw: object) -> can.BusABC:
    return can.Bus(interface=INTERFACE, channel=str(path), role=role, **kw)


def _accept(server: can.BusABC, clients: int) -> None:
    """Let the server accept its clients (it does so while receiving)."""
    deadline = time.monotonic() + 2.0
    while len(server._peers) < clients and time.monotonic() < deadline:  # type: ignore[attr-defined]
        server.recv(0.01)


Network = Callable[[int], tuple[can.BusABC, list[can.BusABC]]]


@pytest.fixture
def network(path: Path) -> Iterator[Network]:
    """``network(k)``: a server and k connected clients, all shut down after the test."""
    with ExitStack() as stack:

        def make(clients: int) -> tuple[can.BusABC, list[can.BusABC]]:
            server = _bus(path, "server")
            stack.callback(server.shutdown)
            members = []
            for k in range(clients):
                bus = _bus(path, bitrate=1_000_000) if k == 0 else _bus(path)
                stack.callback(bus.shutdown)
                members.append(bus)
            _accept(server, clients)
            return server, members

        yield make


def _msg(can_id: int, data: bytes = b"", **kw: object) -> can.Message:
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=False, **kw)


def test_registered_with_python_can() -> None:
    assert INTERFACE in can.VALID_INTERFACES


def test_every_bus_sees_the_others_frames_never_its_own(network: Network) -> None:
    server, (a, b) = network(2)  # a was opened with a bitrate: accepted and ignored
    a.send(_msg(0x80, b"\x07"))
    for bus in (server, b):
        got = bus.recv(1.0)
        assert got is not None and got.arbitration_id == 0x80 and bytes(got.data) == b"\x07"
        assert got.is_rx and not got.is_extended_id
    assert a.recv(0.05) is None  # no echo of its own frame

    server.send(_msg(0x181, bytes(range(8))))
    for bus in (a, b):
        got = bus.recv(1.0)
        assert got is not None and bytes(got.data) == bytes(range(8)) and got.dlc == 8
    assert server.recv(0.05) is None


def test_frame_kinds_survive_the_trip(network: Network) -> None:
    server, (client,) = network(1)
    sent = [
        can.Message(arbitration_id=0x1ABCDE0F, data=b"\x01\x02", is_extended_id=True),
        can.Message(arbitration_id=0x601, is_remote_frame=True, dlc=8, is_extended_id=False),
        can.Message(arbitration_id=0x40, data=bytes(8), is_error_frame=True),
        _msg(0x000, b""),
    ]
    for m in sent:
        client.send(m)
    for m in sent:
        got = server.recv(1.0)
        assert got is not None
        assert got.arbitration_id == m.arbitration_id
        assert got.is_extended_id == m.is_extended_id
        assert got.is_remote_frame == m.is_remote_frame
        assert got.is_error_frame == m.is_error_frame
        assert got.dlc == m.dlc
        if not m.is_remote_frame:
            assert bytes(got.data) == bytes(m.data)


def test_a_frame_is_stamped_when_it_was_sent(network: Network) -> None:
    """As on the virtual bus (and a CAN interface's hardware stamp): not when it was read."""
    server, (client,) = network(1)
    before = time.time()
    client.send(_msg(0x80, b"\x01"))
    after = time.time()
    time.sleep(0.05)  # a reader that gets round to it late
    got = server.recv(1.0)
    assert got is not None and before <= got.timestamp <= after


def test_order_is_kept_per_sender(network: Network) -> None:
    server, (client,) = network(1)
    for k in range(500):
        client.send(_msg(0x200, k.to_bytes(2, "little")))
    got = [int.from_bytes(bytes(server.recv(1.0).data), "little") for _ in range(500)]  # type: ignore[union-attr]
    assert got == list(range(500))


def test_a_reader_that_stops_reading_loses_frames_but_blocks_nobody(network: Network) -> None:
    server, (idle,) = network(1)
    t0 = time.monotonic()
    for _ in range(20_000):
        server.send(_msg(0x181, bytes(8)))
    assert time.monotonic() - t0 < 10.0  # never blocked on the full buffer
    assert server.overflows > 0  # type: ignore[attr-defined]
    received = 0
    while idle.recv(0.0) is not None:
        received += 1
    assert received + server.overflows == 20_000  # type: ignore[attr-defined]


def test_server_gone_ends_the_client_and_client_gone_is_forgotten(path: Path) -> None:
    server = _bus(path, "server")
    a, b = _bus(path), _bus(path)
    _accept(server, 2)
    a.shutdown()
    b.send(_msg(0x80))
    assert server.recv(1.0) is not None  # still serving the other client
    server.shutdown()
    assert not path.exists()  # the server removes its socket file
    with pytest.raises(can.CanOperationError, match="went away"):
        b.recv(1.0)
    with pytest.raises(can.CanOperationError):
        b.send(_msg(0x80))
    b.shutdown()


def test_socket_file_is_private_and_paths_are_checked(path: Path) -> None:
    server = _bus(path, "server")
    try:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        with pytest.raises(can.CanInitializationError, match="listening"):
            _bus(path, "server")
    finally:
        server.shutdown()

    # a socket left behind by a killed server is replaced
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    stale.bind(str(path))
    stale.close()
    assert path.exists()
    _bus(path, "server").shutdown()

    path.write_text("not a socket")
    with pytest.raises(can.CanInitializationError, match="not a socket"):
        _bus(path, "server")
    assert path.read_text() == "not a socket"  # left alone

    with pytest.raises(can.CanInitializationError, match="role"):
        IpcBus(path, role="master")


def test_no_server_is_a_bus_error_naming_the_path(path: Path) -> None:
    cfg = BusConfig(INTERFACE, str(path), extra={"connect_timeout_s": 0.1})
    with pytest.raises(BusError, match=str(path)):
        open_bus(cfg)


def test_frames_cross_a_process_boundary(path: Path) -> None:
    """A client in another interpreter answers the server's SYNC."""
    server = _bus(path, "server")
    try:
        code = (
            "import can, sys\n"
            f"b = can.Bus(interface={INTERFACE!r}, channel={str(path)!r})\n"
            "m = b.recv(10.0)\n"
            "b.send(can.Message(arbitration_id=0x181, data=bytes(m.data) * 2,"
            " is_extended_id=False))\n"
            "b.shutdown()\n"
        )
        child = subprocess.Popen([sys.executable, "-c", code])
        _accept(server, 1)
        server.send(_msg(0x80, b"\x2a"))
        reply = None
        deadline = time.monotonic() + 20.0
        while reply is None and time.monotonic() < deadline:
            reply = server.recv(0.5)
        assert child.wait(20.0) == 0
        assert reply is not None and reply.arbitration_id == 0x181
        assert bytes(reply.data) == b"\x2a\x2a"
    finally:
        server.shutdown()
