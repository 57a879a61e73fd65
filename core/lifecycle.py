"""Releasing what a run holds: ``with``-block bases and the never-raising teardown step.

Objects that hold a bus, a process, a thread or a temporary folder are used as context managers
(or opened and closed by hand). :class:`Closing` is the base of those a ``with`` block releases
through ``close()``; :class:`Running` of those it starts on entering and stops on leaving. The
teardown itself runs on the way down from a fault, where a second error must not hide the
first: :func:`release_quietly` runs one step of it and logs a failure instead of raising.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from types import TracebackType
from typing import Self


def release_quietly(
    step: Callable[[], object], what: str, logger: logging.Logger, level: int = logging.ERROR
) -> None:
    """Run one teardown step; log its failure as ``"<what> failed: <error>"`` instead of raising.

    Parameters
    ----------
    step
        The step, e.g. ``network.disconnect``.
    what
        What the step does, for the log line (``"closing the master"``).
    logger
        Where the failure is logged.
    level
        Logging level of the failure (default ``ERROR``).
    """
    try:
        step()
    except Exception as exc:
        logger.log(level, "%s failed: %s", what, exc)


class Closing:
    """Base of an object a ``with`` block releases: leaving the block calls :meth:`close`
    (whether or not the block raised). What entering gives is the subclass's ``__enter__``
    (the object itself, or what opening it made)."""

    def close(self) -> None:
        """Release everything the object holds (subclasses; should never raise)."""
        raise NotImplementedError

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class Running(Closing):
    """Base of an object a ``with`` block runs: entering calls :meth:`start`, leaving
    :meth:`stop` (also reachable as :meth:`close`)."""

    def start(self) -> None:
        """Start (subclasses)."""
        raise NotImplementedError

    def stop(self) -> None:
        """Stop and release everything (subclasses; should never raise)."""
        raise NotImplementedError

    def close(self) -> None:
        """The same as :meth:`stop`."""
        self.stop()

    def __enter__(self) -> Self:
        self.start()
        return self
