"""Tests on a Linux kernel CAN interface ``vcan0`` (python-can's ``socketcan`` interface).

They run in a QEMU guest with a Debian kernel (``make test-vcan``, see ``tests/vcan/run``): the
host kernel here has no CAN support. Anywhere without a ``vcan0`` interface (the main ``pytest``
run, a laptop without the vcan module) every test of this folder is skipped with the reason.
"""

from __future__ import annotations

import signal
import socket
import subprocess
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import pytest

CHANNEL = "vcan0"
HAVE_VCAN = Path(f"/sys/class/net/{CHANNEL}").exists()
HERE = Path(__file__).resolve().parent

#: Socket receive buffer of the test buses: under emulation the guest passes only 800-2 500
#: frames/s, and with the default (212 992 bytes) bursts of 10 000 frames lost up to 20 %.
RCVBUF_BYTES = 4 * 1024 * 1024
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if HAVE_VCAN:
        return
    skip = pytest.mark.skip(
        reason=f"no {CHANNEL} interface (the host kernel has no CAN): run `make test-vcan`, "
        "which boots a QEMU guest with vcan0 and runs tests/vcan there"
    )
    for item in items:
        if HERE in Path(str(item.path)).resolve().parents:
            item.add_marker(skip)


def _open_vcan(**kwargs: Any) -> can.BusABC:
    bus = can.Bus(interface="socketcan", channel=CHANNEL, **kwargs)
    try:
        sock = bus.socket  # python-can's SocketcanBus exposes its raw socket
        sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, RCVBUF_BYTES)
        # the kernel doubles the value it is given and reports the doubled size
        got = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        assert got >= RCVBUF_BYTES, f"receive buffer {got} bytes"
    except BaseException:
        bus.shutdown()
        raise
    return bus


@pytest.fixture
def open_vcan() -> Iterator[Callable[..., can.BusABC]]:
    """Opens python-can ``socketcan`` buses on vcan0 with a 4 MB receive buffer
    (SO_RCVBUFFORCE); keyword arguments go to :class:`can.Bus`. All are shut down after the test.
    """
    buses: list[can.BusABC] = []

    def open_(**kwargs: Any) -> can.BusABC:
        bus = _open_vcan(**kwargs)
        buses.append(bus)
        return bus

    yield open_
    for bus in buses:
        bus.shutdown()


@contextmanager
def _candump(args: list[str], out: Path, stop_timeout: float) -> Iterator[subprocess.Popen[bytes]]:
    """``candump *args`` writing to the file ``out`` while the block runs; stopped with SIGINT
    after it (killed if it has not ended within ``stop_timeout`` seconds)."""
    with out.open("wb") as fh:
        proc = subprocess.Popen(["candump", *args], stdout=fh)
    try:
        yield proc
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(stop_timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture(scope="session")
def candump() -> Callable[..., Any]:
    """Runs ``candump`` beside a test: ``with candump(args, out_file, stop_timeout) as proc:``."""
    return _candump
