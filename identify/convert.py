"""``drivegain convert csv``: import positions and currents recorded elsewhere into a run log.

The input is two CSV files with one column per joint (an optional header row, then one row per
sample at a fixed rate), like the real TX-40 recording: motor-side positions in rad and
motor-side torques in N·m. Positions are stored joint side, ``q = K⁻¹ q_m``. What the log calls
``current_reference`` is the drive signal ``v`` with ``V(v) @ gains = tau`` (model.md, eq. 21):

- currents (A): stored as they are; the gains are the drive gains (N·m/A).
- motor torques (``--torque --motor-side``): ``v = tau_m``. Joint torques are
  ``tau = Kᵀ tau_m = V(tau_m) @ N``, so the "gains" of this log are the gear ratios N; the
  metadata says so (``current_unit``, ``gains_hint = gear_ratio``).
- joint torques (``--torque`` without ``--motor-side``): converted to motor torques
  ``tau_m = K⁻ᵀ tau`` and stored as above.

The log is written to ``OUT.part`` and renamed when complete; on any error nothing is left.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
from array import array
from pathlib import Path

import numpy as np

from drivegain.config.payload import Payload, load_payload
from drivegain.config.robot import Robot, load_robot
from drivegain.dynamics.transmission import motor_to_joint
from drivegain.errors import DataError, InputError
from drivegain.fileio import reading
from drivegain.formats.log import run_metadata, utc_iso
from drivegain.formats.logwriter import write_run

#: Delimiters of the CSV files read, looked for in this order in the first line.
CSV_DELIMITERS = (",", ";", "\t")


def csv_delimiter(first_line: str) -> str:
    """The delimiter of a CSV file (:data:`CSV_DELIMITERS`) from its first line; comma if none."""
    return next((d for d in CSV_DELIMITERS if d in first_line), ",")


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def is_header(fields: list[str]) -> bool:
    """Whether a CSV row is a header row: not all of its fields are numbers."""
    return not all(_is_float(f) for f in fields)


def robot_and_payload(
    robot: Robot | str | Path, payload: Payload | str | Path | None, *, acquisition: bool
) -> tuple[Robot, Payload | None]:
    """The robot and the payload of a conversion, loaded from their TOML files where given as
    paths (``acquisition`` as for :func:`~drivegain.config.robot.load_robot`)."""
    rob = robot if isinstance(robot, Robot) else load_robot(robot, acquisition=acquisition)
    pay = (
        payload if payload is None or isinstance(payload, Payload) else load_payload(payload, rob.n)
    )
    return rob, pay


def toml_attachments(robot: Robot, payload: Payload | None) -> list[tuple[str, str, bytes]]:
    """The robot's and the payload's TOML files, where they were loaded from one, as log
    attachments ``(name, media type, data)``."""
    attachments: list[tuple[str, str, bytes]] = []
    for src in (robot.source, None if payload is None else payload.source):
        if src is not None and Path(src).is_file():
            attachments.append((Path(src).name, "application/toml", Path(src).read_bytes()))
    return attachments


def read_csv_columns(path: str | Path, n_columns: int) -> tuple[list[str], np.ndarray]:
    """Read a numeric CSV with ``n_columns`` columns and an optional header row.

    The delimiter (comma, semicolon or tab) is taken from the first line. Trailing empty lines
    are ignored.

    Returns
    -------
    tuple
        Column names (``column 1`` ... when there is no header) and the values, (N, n_columns).

    Raises
    ------
    DataError
        One line naming the file, the line number and the column: file missing, not text,
        ragged row, non-numeric or non-finite value, no data.
    """
    p = Path(path)
    with reading(p, error=DataError, expected="a CSV file"):
        text = p.read_text(encoding="utf-8-sig")
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise DataError("empty file, expected CSV data", file=p)
    reader = csv.reader(lines, delimiter=csv_delimiter(lines[0]))
    values = array("d")
    header: list[str] | None = None
    rows = 0
    for lineno, fields in enumerate(reader, start=1):
        if lineno == 1 and is_header(fields):
            header = [f.strip() for f in fields]
            if len(header) != n_columns:
                raise DataError(
                    f"header has {len(header)} columns, expected {n_columns} (one per joint)",
                    file=p,
                    key="line 1",
                )
            continue
        if len(fields) != n_columns:
            what = "empty line" if not fields else f"{len(fields)} fields"
            raise DataError(
                f"{what}, expected {n_columns} (one per joint)", file=p, key=f"line {lineno}"
            )
        for c, f in enumerate(fields):
            try:
                v = float(f)
            except ValueError:
                name = header[c] if header else f"column {c + 1}"
                raise DataError(
                    f"column {c + 1} ({name}): {f.strip()!r} is not a number",
                    file=p,
                    key=f"line {lineno}",
                ) from None
            if not math.isfinite(v):
                name = header[c] if header else f"column {c + 1}"
                raise DataError(
                    f"column {c + 1} ({name}): {f.strip()!r} is not finite",
                    file=p,
                    key=f"line {lineno}",
                )
            values.append(v)
        rows += 1
    if rows == 0:
        raise DataError("no data rows after the header", file=p)
    names = header if header is not None else [f"column {c + 1}" for c in range(n_columns)]
    return names, np.frombuffer(values, dtype=float).reshape(rows, n_columns).copy()


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def convert_csv(
    positions_csv: str | Path,
    currents_csv: str | Path,
    rate_hz: float,
    robot: Robot | str | Path,
    *,
    motor_side: bool,
    torque: bool,
    run: str = "unloaded",
    out: str | Path,
    payload: Payload | str | Path | None = None,
) -> Path:
    """Convert a CSV recording into a run log (contracts §4).

    Parameters
    ----------
    positions_csv
        One column per joint: positions in rad, motor side if ``motor_side`` else joint side.
    currents_csv
        One column per drive: current references (A), or torques (N·m) if ``torque``: motor
        torques if ``motor_side`` else joint torques.
    rate_hz
        Sample rate, Hz.
    robot
        The robot (or its TOML file): transmission and joint names.
    motor_side, torque
        See above.
    run
        Run label (``unloaded``, ``loaded``, ...).
    out
        The ``.mcap`` file to write.
    payload
        The payload fixed to the robot during the run (or its TOML file), if any.

    Returns
    -------
    pathlib.Path
        The log written.

    Raises
    ------
    DataError, InputError, ConfigError
        Bad files or values (one line naming file, line and column); nothing is written.
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise InputError(f"must be a positive number of Hz, got {rate_hz}", key="--rate")
    rob, pay = robot_and_payload(robot, payload, acquisition=True)
    pos_path, cur_path, out_path = Path(positions_csv), Path(currents_csv), Path(out)
    if not out_path.parent.is_dir():
        raise InputError("output folder does not exist", file=out_path.parent, key="--out")
    if not run.strip():
        raise InputError("run label must not be empty", key="--run")

    pos_names, raw_pos = read_csv_columns(pos_path, rob.n)
    cur_names, raw_cur = read_csv_columns(cur_path, rob.n)
    if raw_pos.shape[0] != raw_cur.shape[0]:
        raise DataError(
            f"{raw_pos.shape[0]} rows, but {cur_path} has {raw_cur.shape[0]}: the files must "
            "hold the same samples",
            file=pos_path,
        )
    n_samples = raw_pos.shape[0]
    if n_samples < 2:
        raise DataError("a run needs at least 2 samples", file=pos_path)

    q = motor_to_joint(rob, raw_pos) if motor_side else raw_pos
    k = rob.transmission()
    if torque:
        # v = motor torque: V(v) @ N = Kᵀ tau_m, the joint torque (see module docstring).
        v = raw_cur if motor_side else np.linalg.solve(k.T, raw_cur.T).T
    else:
        v = raw_cur

    extra = {
        "source": "drivegain convert csv",
        "positions_csv": pos_path.name,
        "positions_sha256": _sha256(pos_path),
        "positions_columns": json.dumps(pos_names),
        "currents_csv": cur_path.name,
        "currents_sha256": _sha256(cur_path),
        "currents_columns": json.dumps(cur_names),
        "positions_recorded": "motor side, converted with q = K^-1 q_m" if motor_side else "joint",
        "fields_unavailable": "current,setpoint",
        "started_at_source": "modification time of the positions CSV",
    }
    if torque:
        extra["current_unit"] = "N·m motor torque"
        extra["gains_hint"] = "gear_ratio"
        extra["torques_recorded"] = (
            "motor side" if motor_side else "joint side, converted with tau_m = K^-T tau"
        )
    else:
        extra["current_unit"] = "A"
    mtime = pos_path.stat().st_mtime
    meta = run_metadata(rob, run, pay, 1.0 / rate_hz, utc_iso(mtime), extra)
    attachments = toml_attachments(rob, pay)
    t = np.arange(n_samples) / rate_hz
    start_ns = int(mtime) * 1_000_000_000
    log_time = start_ns + np.rint(np.arange(n_samples) * (1e9 / rate_hz)).astype(np.int64)
    return write_run(
        out_path,
        meta,
        t,
        q,
        v,
        cycle=np.arange(n_samples),
        log_time_ns=log_time,
        attachments=attachments,
    )


def convert_csv_command(args: argparse.Namespace) -> int:
    """Handler of ``drivegain convert csv`` (options in :mod:`drivegain.cli`)."""
    out = convert_csv(
        args.positions,
        args.currents,
        args.rate,
        args.robot,
        motor_side=args.motor_side,
        torque=args.torque,
        run=args.run,
        out=args.out,
        payload=getattr(args, "payload", None),
    )
    from drivegain.formats.logreader import read_run

    log = read_run(out)
    duration = log.t[-1] - log.t[0]
    unit = log.meta.get("current_unit", "A")
    print(
        f"wrote {out}: {log.messages_recovered} samples, {duration:.3f} s at {args.rate:g} Hz, "
        f"{log.n} joints, current_reference in {unit}"
    )
    if log.meta.get("gains_hint") == "gear_ratio":
        print("current_reference holds motor torques: identify with gains = the gear ratios")
    return 0
