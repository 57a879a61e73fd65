"""The fleet table: one row per robot and campaign, from every result in a results folder.

Columns (one row per ``result.json`` found under ``OUT/tasks``):

- ``robot_id``, ``campaign``, ``date`` (ISO 8601), ``status`` (``ok``/``failed``);
- per joint ``gain_<joint>`` and ``gain_<joint>_std``, N·m/A (one standard deviation);
- friction base parameters ``<name>`` and ``<name>_std``: viscous ``Fv<j>`` (N·m·s/rad),
  Coulomb ``Fc<j>`` (N·m), and the coupled motor's ``fvm<j>``/``fcm<j>`` where the robot has them.
  Identification estimates them with the identified gains held fixed, so the σ of its report
  leaves out the gains' own uncertainty; joint j's friction is a torque, i.e. scales with g_j,
  and the table's σ adds g_j's relative σ to first order:
  ``σ = |p|·sqrt((σ_p/p)² + (σ_gj/g_j)²)`` (without it, repeated campaigns of an unchanged
  robot differ by several reported σ: see the fleet tests);
- ``payload_mass``/``payload_mass_std`` (kg) when a loaded run was identified;
- ``residual_norm`` (N·m), ``residual_relative``, ``estimator``, ``gains_source``, ``samples``;
- ``warnings`` (the identification's warnings and a failure's reason, joined by `` | ``),
  ``worker`` and ``seconds`` (wall time of the identification, s).

Every value column ``X`` with a ``X_std`` column is a parameter the drift report compares.
Written as ``fleet.parquet`` and ``fleet.csv`` (pyarrow), each atomically.
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Sequence
from typing import Any

from drivegain.fleet import storage
from drivegain.fleet.task import RESULT, TaskResult

#: Base parameters that are friction: viscous, Coulomb, coupled-motor viscous and Coulomb.
FRICTION = re.compile(r"^(Fv|Fc|fvm|fcm)(\d+)$")
STD = "_std"
#: Columns that describe a row, in this order, before the parameters.
ID_COLUMNS = ("robot_id", "campaign", "date", "status")
TAIL_COLUMNS = (
    "payload_mass",
    "payload_mass_std",
    "residual_norm",
    "residual_relative",
    "estimator",
    "gains_source",
    "samples",
    "warnings",
    "worker",
    "seconds",
)


def load_results(out: str) -> list[TaskResult]:
    """Every task result stored under ``out`` (any campaign, any batch)."""
    found = storage.glob(storage.join(out, "tasks", "*", "*", RESULT))
    return [TaskResult.from_json(storage.read_bytes(f), f) for f in found]


def row(result: TaskResult) -> dict[str, Any]:
    """The fleet-table row of one result (module docstring)."""
    t = result.task
    r: dict[str, Any] = {
        "robot_id": t["robot_id"],
        "campaign": t["campaign"],
        "date": t["date"],
        "status": result.status,
    }
    rep = result.report or {}
    for g in rep.get("gains", []):
        r[f"gain_{g['joint']}"] = g.get("value")
        r[f"gain_{g['joint']}{STD}"] = g.get("std")
    gain_rel = [_rel_std(g) for g in rep.get("gains", [])]
    for b in rep.get("base_parameters", []):
        m = FRICTION.match(b["name"])
        if m:
            r[b["name"]] = b.get("value")
            r[f"{b['name']}{STD}"] = _with_gain(b, gain_rel, int(m.group(2)))
    mass = rep.get("payload", {}).get("mass")
    if isinstance(mass, dict):
        r["payload_mass"], r["payload_mass_std"] = mass.get("value"), mass.get("std")
    residual = rep.get("residual", {})
    method = rep.get("method", {})
    r["residual_norm"] = residual.get("norm")
    r["residual_relative"] = residual.get("relative")
    r["estimator"] = method.get("estimator")
    r["gains_source"] = method.get("gains_source")
    r["samples"] = method.get("samples")
    warnings = list(rep.get("warnings", []))
    if result.error:
        warnings.append(result.error)
    r["warnings"] = " | ".join(str(w) for w in warnings)
    r["worker"] = result.worker
    r["seconds"] = result.seconds
    return r


def _rel_std(g: dict[str, Any]) -> float | None:
    v, s = g.get("value"), g.get("std")
    if not isinstance(v, int | float) or not isinstance(s, int | float) or v == 0:
        return None
    return abs(float(s) / float(v))


def _with_gain(b: dict[str, Any], gain_rel: list[float | None], joint: int) -> float | None:
    """σ of a friction parameter of ``joint`` (1-based) with its gain's relative σ added."""
    v, s = b.get("value"), b.get("std")
    if not isinstance(v, int | float) or not isinstance(s, int | float):
        return None
    rel = gain_rel[joint - 1] if 0 < joint <= len(gain_rel) else None
    if rel is None:
        return float(s)
    return math.hypot(float(s), rel * float(v))


def fleet_rows(results: Sequence[TaskResult]) -> list[dict[str, Any]]:
    """Rows of the fleet table, sorted by robot, then date, then campaign."""
    rows = [row(r) for r in results]
    return sorted(rows, key=lambda r: (r["robot_id"], r["date"], r["campaign"]))


def columns(rows: Sequence[dict[str, Any]]) -> list[str]:
    """All columns of ``rows``: identifiers, parameters (each followed by its σ), the rest."""
    seen: dict[str, None] = {}
    for r in rows:
        for k in r:
            seen.setdefault(k, None)
    params = [
        k for k in seen if k not in ID_COLUMNS and k not in TAIL_COLUMNS and not k.endswith(STD)
    ]
    out = list(ID_COLUMNS)
    for p in params:
        out.append(p)
        if p + STD in seen:
            out.append(p + STD)
    return out + [c for c in TAIL_COLUMNS if c in seen]


def parameters(rows: Sequence[dict[str, Any]]) -> list[str]:
    """The parameter columns (those with a ``_std`` column), in table order."""
    cols = columns(rows)
    return [c for c in cols if c + STD in cols]


def to_arrow(rows: Sequence[dict[str, Any]], cols: Sequence[str] | None = None) -> Any:
    """A ``pyarrow.Table`` of ``rows`` (missing values are nulls)."""
    import pyarrow as pa

    cols = list(cols) if cols is not None else columns(rows)
    return pa.table({c: [r.get(c) for r in rows] for c in cols})


def write_table(table: Any, out: str, stem: str) -> list[str]:
    """Write ``table`` as ``OUT/STEM.parquet`` and ``OUT/STEM.csv``; returns the locations."""
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    written = []
    buf = io.BytesIO()
    pq.write_table(table, buf)
    location = storage.join(out, f"{stem}.parquet")
    storage.write_atomic(location, buf.getvalue())
    written.append(location)
    buf = io.BytesIO()
    pcsv.write_csv(table, buf)
    location = storage.join(out, f"{stem}.csv")
    storage.write_atomic(location, buf.getvalue())
    written.append(location)
    return written
