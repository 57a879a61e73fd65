"""The exception tree of drivegain.

Every error the package raises on purpose derives from :class:`DrivegainError`. Subclasses carry
the context a user needs to fix the cause (file, key, node id); ``str(err)`` is one line that
names it, which is what the command line prints.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any


class DrivegainError(Exception):
    """Root of all drivegain errors."""


class InputError(DrivegainError):
    """Bad user input (files, values, options): the command line exits with status 2.

    Parameters
    ----------
    message
        What is wrong, in one line.
    file
        The file at fault, if any.
    key
        The key (dotted path) or column at fault, if any.
    """

    def __init__(self, message: str, *, file: str | Path | None = None, key: str | None = None):
        self.message = message
        self.file = None if file is None else str(file)
        self.key = key
        super().__init__(self._format())

    def __reduce__(self) -> tuple[Any, tuple[str]]:
        # the default pickling passes only the formatted line back to __init__: file and key
        # would be lost (and the prefix doubled) when an error comes back from a worker process
        return functools.partial(type(self), file=self.file, key=self.key), (self.message,)

    def _format(self) -> str:
        where = []
        if self.file is not None:
            where.append(self.file)
        if self.key is not None:
            where.append(f"key '{self.key}'")
        prefix = ": ".join(where)
        return f"{prefix}: {self.message}" if prefix else self.message


class ConfigError(InputError):
    """A configuration file (robot, payload, bus, acquisition) is malformed."""


class DataError(InputError):
    """A data file (log, CSV, trajectory) is unreadable or inconsistent."""


class ModelError(DrivegainError):
    """The robot model cannot be built or evaluated (e.g. an unsupported joint type)."""


class IdentificationError(DrivegainError):
    """The identification problem is ill-posed or cannot be solved with the data given."""


class TrajectoryError(DrivegainError):
    """An excitation or motion cannot be made to respect the limits."""


class DriveError(DrivegainError):
    """A fault on one drive or on the bus.

    Parameters
    ----------
    message
        What happened.
    node
        CANopen node id of the drive, or ``None`` for a bus-wide fault.
    state
        The drive's CiA 402 state when the fault was seen, if known: a
        ``drivegain.drivers.cia402.State``, a string enum whose value is the state's name (so
        the message reads "state FAULT" and it compares equal to ``"FAULT"``).
    code
        Error code (EMCY code, SDO abort code, ...) if any.
    """

    def __init__(
        self,
        message: str,
        *,
        node: int | None = None,
        state: str | None = None,
        code: int | None = None,
    ):
        self.message = message
        self.node = node
        self.state = state
        self.code = code
        parts = []
        if node is not None:
            parts.append(f"node {node}")
        if state is not None:
            parts.append(f"state {state}")
        if code is not None:
            parts.append(f"code 0x{code:04X}")
        ctx = f" ({', '.join(parts)})" if parts else ""
        super().__init__(f"{message}{ctx}")


class BusError(DriveError):
    """The CAN bus itself failed (bus-off, error frames, interface gone)."""


class OperatorStop(DrivegainError):
    """The run was stopped by the operator (signal or control request)."""


class UsageError(DrivegainError):
    """The package was called in a way its API does not allow (wrong array shapes, a writer
    used after it finished): a fault in the calling code, not in a file or a drive."""
