"""A run request, read and checked before the bus is touched: files, label, output, bus load.

Everything here can refuse a request with an :class:`~drivegain.errors.InputError` naming the
file or key, and nothing here writes a file or talks to a drive: a daemon answers a bad ``run``
request at once, and a foreground run fails before booting the cell.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from drivegain.acquire.checks import check_bus_load, check_excitation
from drivegain.acquire.config import AcquisitionConfig
from drivegain.config.payload import Payload, load_payload
from drivegain.drivers.bus import BusLoad
from drivegain.errors import InputError
from drivegain.excite.trajectory import ExcitationFile, load_trajectory

_LABEL = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


@dataclass(frozen=True)
class RunRequest:
    """What to run: trajectory JSON, log to write (``.mcap``), run label, payload TOML."""

    trajectory: Path
    out: Path
    label: str | None = None
    payload: Path | None = None


@dataclass(frozen=True)
class PreparedRun:
    """A request whose files were read and checked (nothing written, bus untouched)."""

    request: RunRequest
    label: str
    excitation: ExcitationFile
    payload: Payload | None
    attachments: tuple[tuple[str, str, bytes], ...]
    bus_load: BusLoad
    warnings: tuple[str, ...]


def validate_label(label: str) -> str:
    """A run label usable in a file name.

    Raises
    ------
    InputError
        The label is empty or has characters other than letters, digits, ``_ . -``.
    """
    if not _LABEL.match(label):
        raise InputError(
            f"run label {label!r} must be 1-64 letters, digits, '_', '.' or '-'", key="label"
        )
    return label


def prepare_run(cfg: AcquisitionConfig, request: RunRequest) -> PreparedRun:
    """Read and check everything that does not need the bus; write nothing.

    Raises
    ------
    InputError
        A bad trajectory, payload, output path or label, or a bus that cannot carry the cycle.
    """
    out = request.out
    if out.suffix != ".mcap":
        raise InputError("the log must be a .mcap file", file=out)
    for existing in (out, out.with_name(out.name + ".part")):
        if existing.exists():
            raise InputError("already exists (a log is never overwritten)", file=existing)
    if out.parent.exists() and not out.parent.is_dir():
        raise InputError("is not a directory", file=out.parent)
    robot = cfg.robot
    traj_bytes = _read_bytes(request.trajectory)
    excitation = load_trajectory(request.trajectory)
    excitation.check_robot(robot)
    check_excitation(robot, excitation.fourier, cfg.period_s, file=request.trajectory)
    payload = None
    attachments: list[tuple[str, str, bytes]] = [
        (cfg.robot_path.name, "application/toml", _read_bytes(cfg.robot_path))
    ]
    if request.payload is not None:
        payload_bytes = _read_bytes(request.payload)
        payload = load_payload(request.payload)
        attachments.append((request.payload.name, "application/toml", payload_bytes))
    attachments.append((request.trajectory.name, "application/json", traj_bytes))
    label = validate_label(request.label or ("loaded" if payload is not None else "unloaded"))
    load, warning = check_bus_load(
        robot.n, cfg.period_s, cfg.bus.bitrate, warn=cfg.bus_load_warn, config=cfg.source
    )
    return PreparedRun(
        request=request,
        label=label,
        excitation=excitation,
        payload=payload,
        attachments=tuple(attachments),
        bus_load=load,
        warnings=(warning,) if warning else (),
    )


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputError("file not found", file=path) from None
    except IsADirectoryError:
        raise InputError("is a directory, expected a file", file=path) from None
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror})", file=path) from None
