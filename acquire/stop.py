"""Operator stop requests shared between signal handlers, the daemon and the cycle loop.

Signal handlers run between bytecodes of the main thread, so the request uses no lock (a handler
taking a lock the interrupted code holds would deadlock); the cycle loop only polls it.
"""

from __future__ import annotations

import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType


class StopRequest:
    """A stop asked by the operator: the first request brings the robot smoothly to rest, a second
    one while stopping asks for an immediate quick stop."""

    def __init__(self) -> None:
        self.count = 0
        self.reason: str | None = None

    def request(self, reason: str) -> None:
        """Ask for a stop (safe in a signal handler)."""
        if self.reason is None:
            self.reason = reason
        self.count += 1

    @property
    def requested(self) -> bool:
        return self.count > 0

    @property
    def urgent(self) -> bool:
        """A second request arrived: quick stop now."""
        return self.count > 1


@contextmanager
def stop_on_signals(
    stop: StopRequest, on_signal: Callable[[str], None] | None = None
) -> Iterator[StopRequest]:
    """Turn SIGINT and SIGTERM into :meth:`StopRequest.request` while the block runs.

    Must be entered on the main thread (Python delivers signals there); the previous handlers are
    restored on exit.
    """

    def handler(signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        stop.request(name)
        if on_signal is not None:
            on_signal(name)

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
