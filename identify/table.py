"""``drivegain convert table``: one table with a time column (CSV or Parquet) → a run log.

Real recordings come as one table: a time column and many others (positions, velocities,
actual and target currents, torques, ...). The columns for each log field are chosen by name or
by number, a row range or a time window keeps part of it, and the log gets the table's real
time stamps (``t`` = time − time of the first row kept; ``sync_period_s`` = the mean step),
so ``identify`` detects an irregular time base and resamples it (docs/model.md).

Expected layout (one row per sample, a header row naming the columns)::

    time,q1,q2,q3,q4,q5,q6,iref1,...,iref6,i1,...,i6
    0.000,0.10,-1.20,...
    0.010,0.11,-1.19,...

    drivegain convert table --input run.csv --time time --position 'q{}' \\
        --current-reference 'iref{}' --current 'i{}' --robot ur5 --run unloaded --out a.mcap

A column list is comma-separated names or 1-based column numbers (``2,3,4,5,6,7``), or one
name with ``{}`` standing for the joint number 1..n (``q{}``).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivegain.config.payload import Payload
from drivegain.config.robot import Robot
from drivegain.dynamics.transmission import motor_to_joint
from drivegain.errors import DataError, InputError
from drivegain.fileio import check_output
from drivegain.formats.log import run_metadata, utc_iso
from drivegain.formats.logwriter import write_run
from drivegain.identify.convert import csv_delimiter, is_header, robot_and_payload, toml_attachments

#: Seconds per unit of the time column.
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}


@dataclass(frozen=True)
class Table:
    """Columns of a table by name (all kept as text until chosen)."""

    path: Path
    names: list[str]
    header: bool
    columns: dict[int, list[str]] | None  # CSV: raw text per column index
    arrow: object | None = None  # Parquet: the pyarrow table

    def index(self, spec: str, option: str) -> int:
        """Column index (0-based) of a name or a 1-based number."""
        s = spec.strip()
        if s in self.names:
            return self.names.index(s)
        if s.isdigit() and 1 <= int(s) <= len(self.names):
            return int(s) - 1
        known = ", ".join(self.names[:12]) + (" ..." if len(self.names) > 12 else "")
        raise InputError(
            f"no column {s!r} (columns: {known}; or a number 1..{len(self.names)})",
            file=self.path,
            key=option,
        )

    def values(self, index: int) -> np.ndarray:
        """The column as floats.

        Raises
        ------
        DataError
            A value that is not a finite number (naming the row and column).
        """
        name = self.names[index]
        if self.arrow is not None:
            col = self.arrow.column(index)  # type: ignore[attr-defined]
            try:
                out = np.asarray(col.to_numpy(zero_copy_only=False), dtype=float)
            except (TypeError, ValueError):
                raise DataError(f"column {name!r} is not numeric", file=self.path) from None
        else:
            assert self.columns is not None
            texts = self.columns[index]
            out = np.empty(len(texts))
            for r, text in enumerate(texts):
                try:
                    out[r] = float(text)
                except ValueError:
                    line = r + 1 + int(self.header)
                    raise DataError(
                        f"column {name!r}: {text.strip()!r} is not a number",
                        file=self.path,
                        key=f"line {line}",
                    ) from None
        bad = np.flatnonzero(~np.isfinite(out))
        if bad.size:
            raise DataError(
                f"column {name!r}: not a finite number in row {int(bad[0]) + 1}", file=self.path
            )
        return out


def read_table(path: str | Path) -> Table:
    """Read a CSV (header row optional) or, with pyarrow, a Parquet file.

    Raises
    ------
    DataError
        Missing or unreadable file, ragged rows, no data.
    """
    p = Path(path)
    if not p.is_file():
        raise DataError("file not found" if not p.exists() else "not a file", file=p)
    if p.suffix.lower() in (".parquet", ".pq"):
        try:
            import pyarrow.parquet as pq
        except ImportError:
            raise InputError(
                "reading Parquet needs pyarrow (pip install pyarrow)", file=p
            ) from None
        try:
            arrow = pq.read_table(p)
        except Exception as exc:  # pyarrow's errors have no common base worth naming
            raise DataError(f"not a readable Parquet file ({exc})", file=p) from None
        if arrow.num_rows == 0:
            raise DataError("no rows", file=p)
        return Table(p, list(arrow.column_names), True, None, arrow)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise DataError("not a UTF-8 text file", file=p) from None
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if not lines:
        raise DataError("empty file, expected CSV data", file=p)
    rows = list(csv.reader(lines, delimiter=csv_delimiter(lines[0])))
    header = is_header(rows[0])
    width = len(rows[0])
    names = [f.strip() for f in rows[0]] if header else [str(c + 1) for c in range(width)]
    data = rows[1:] if header else rows
    if not data:
        raise DataError("no data rows after the header", file=p)
    for r, fields in enumerate(data):
        if len(fields) != width:
            raise DataError(
                f"{len(fields)} fields, expected {width}", file=p, key=f"line {r + 1 + header}"
            )
    columns = {c: [row[c] for row in data] for c in range(width)}
    return Table(p, names, header, columns)


def column_list(spec: str, n: int, table: Table, option: str) -> list[int]:
    """Column indices for ``n`` joints from ``spec`` (see the module docstring).

    Raises
    ------
    InputError
        Wrong count or unknown column.
    """
    if "{}" in spec:
        items = [spec.replace("{}", str(j + 1)) for j in range(n)]
    else:
        items = [s for s in spec.split(",") if s.strip()]
    if len(items) != n:
        raise InputError(f"expected {n} columns (one per joint), got {len(items)}", key=option)
    return [table.index(s, option) for s in items]


def _rows(
    t: np.ndarray, rows: str | None, start: float | None, end: float | None, path: Path
) -> np.ndarray:
    """Mask of the rows kept: ``rows`` ``A:B`` (1-based, inclusive) and ``start <= t <= end``."""
    keep = np.ones(t.size, dtype=bool)
    if rows is not None:
        a, sep, b = rows.partition(":")
        try:
            lo = int(a) if a.strip() else 1
            hi = int(b) if b.strip() else t.size
        except ValueError:
            raise InputError(
                f"expected FIRST:LAST row numbers, got {rows!r}", key="--rows"
            ) from None
        if not sep or not 1 <= lo <= hi <= t.size:
            raise InputError(f"expected FIRST:LAST within 1..{t.size}, got {rows!r}", key="--rows")
        keep[: lo - 1] = False
        keep[hi:] = False
    if start is not None:
        keep &= t >= start
    if end is not None:
        keep &= t <= end
    if keep.sum() < 2:
        raise DataError("fewer than 2 rows left by --rows/--start/--end", file=path)
    return keep


def convert_table(
    table_path: str | Path,
    robot: Robot | str | Path,
    *,
    time: str,
    position: str,
    current_reference: str,
    out: str | Path,
    current: str | None = None,
    setpoint: str | None = None,
    time_unit: str = "s",
    rows: str | None = None,
    start: float | None = None,
    end: float | None = None,
    motor_side: bool = False,
    run: str = "unloaded",
    payload: Payload | str | Path | None = None,
) -> Path:
    """Convert one table with a time column into a run log (contracts §4).

    Parameters
    ----------
    table_path
        CSV or Parquet file.
    robot
        The robot (or its TOML): joint names, transmission.
    time
        Time column (name or 1-based number), in ``time_unit``.
    position, current_reference, current, setpoint
        Column lists (see the module docstring): positions (rad), current references (A),
        measured currents (A), commanded positions (rad).
    out
        The ``.mcap`` to write; never overwritten.
    time_unit
        ``s``, ``ms``, ``us`` or ``ns``.
    rows
        ``FIRST:LAST`` 1-based data rows kept (either end may be empty).
    start, end
        Time window kept, s from the first row's time.
    motor_side
        Positions and set-points are motor angles (rad): converted with q = K⁻¹ q_m.
    run
        Run label (``unloaded``, ``loaded``, ...).
    payload
        The payload fixed to the robot during the run (attached to the log), if any.

    Returns
    -------
    pathlib.Path
        The log written.

    Raises
    ------
    InputError, DataError, ConfigError
        One line naming the file, option, row or column; nothing is written.
    """
    out_path = check_output(out, suffix=".mcap")
    if time_unit not in TIME_UNITS:
        raise InputError(f"expected one of {', '.join(TIME_UNITS)}", key="--time-unit")
    if not run.strip():
        raise InputError("run label must not be empty", key="--run")
    rob, pay = robot_and_payload(robot, payload, acquisition=False)
    tab = read_table(table_path)
    n = rob.n
    t_all = tab.values(tab.index(time, "--time")) * TIME_UNITS[time_unit]
    t_rel = t_all - t_all[0]
    keep = _rows(t_rel, rows, start, end, tab.path)
    t = t_all[keep]
    steps = np.diff(t)
    if np.any(steps <= 0):
        r = int(np.flatnonzero(steps <= 0)[0])
        raise DataError(
            f"time column {time!r} does not increase after kept row {r + 1}", file=tab.path
        )

    def pick(spec: str | None, option: str) -> np.ndarray | None:
        if spec is None:
            return None
        idx = column_list(spec, n, tab, option)
        return np.column_stack([tab.values(i)[keep] for i in idx])

    q = pick(position, "--position")
    v = pick(current_reference, "--current-reference")
    assert q is not None and v is not None
    i_meas = pick(current, "--current")
    sp = pick(setpoint, "--setpoint")
    if motor_side:
        q = motor_to_joint(rob, q)
        sp = None if sp is None else motor_to_joint(rob, sp)
    rel = t - t[0]
    period = float(rel[-1]) / (rel.size - 1)
    digest = hashlib.sha256(tab.path.read_bytes()).hexdigest()
    extra = {
        "source": "drivegain convert table",
        "table": tab.path.name,
        "table_sha256": digest,
        "time_column": time,
        "time_unit": time_unit,
        "columns": json.dumps(
            {
                "position": position,
                "current_reference": current_reference,
                "current": current,
                "setpoint": setpoint,
            }
        ),
        "positions_recorded": "motor side, converted with q = K^-1 q_m" if motor_side else "joint",
        "current_unit": "A",
        "sync_period_source": "mean step of the time column",
        "started_at_source": "modification time of the table",
    }
    mtime = tab.path.stat().st_mtime
    meta = run_metadata(rob, run, pay, period, utc_iso(mtime), extra)
    start_ns = int(mtime) * 1_000_000_000
    return write_run(
        out_path,
        meta,
        rel,
        q,
        v,
        i_meas,
        sp,
        cycle=np.arange(rel.size),
        log_time_ns=start_ns + np.rint(rel * 1e9).astype(np.int64),
        attachments=toml_attachments(rob, pay),
    )


def convert_table_command(args: argparse.Namespace) -> int:
    """Handler of ``drivegain convert table`` (options in :mod:`drivegain.cli`)."""
    out = convert_table(
        args.input,
        args.robot,
        time=args.time,
        position=args.position,
        current_reference=args.current_reference,
        current=args.current,
        setpoint=args.setpoint,
        out=args.out,
        time_unit=args.time_unit,
        rows=args.rows,
        start=args.start,
        end=args.end,
        motor_side=args.motor_side,
        run=args.run,
        payload=args.payload,
    )
    from drivegain.formats.logreader import read_run

    log = read_run(out)
    steps = np.diff(log.t)
    spread = float(np.std(steps) / np.mean(steps)) if steps.size else math.nan
    print(
        f"wrote {out}: {log.messages_recovered} samples, {log.t[-1]:.3f} s, mean step "
        f"{1e3 * log.sync_period_s:.4g} ms (spread {100 * spread:.2g} %), {log.n} joints"
    )
    return 0
