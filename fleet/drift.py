"""Drift of each robot's parameters against its baseline campaign, in standard deviations.

For a robot, parameter p, its baseline campaign b and a later campaign c::

    z = (p_c − p_b) / sqrt(σ_b² + σ_c²)

(σ: one standard deviation as in the fleet table; the two campaigns' estimates are
independent). The parameters compared are the fleet table's gains and friction (the payload's
mass is the calibration mass, not the robot's). A parameter is flagged when
``|z| > threshold``. With honest σ a threshold of 5 flags an unchanged parameter about once in
1.7 million comparisons; identification's σ are about 13 % optimistic (docs/validation.md),
which the default leaves room for.

Written into the results folder: ``drift.parquet``/``drift.csv`` (one row per robot, campaign
and parameter), ``drift.json`` (the flagged changes and each robot's baseline) and
``drift/ROBOT_ID.png`` (z per parameter and campaign, threshold marked).
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from drivegain.fleet import storage
from drivegain.fleet.table import STD, fleet_rows, load_results, parameters, to_arrow, write_table

#: Table parameters that are not the robot's own: the payload is the calibration mass.
NOT_COMPARED = ("payload_",)


@dataclass(frozen=True)
class Drift:
    """One parameter of one robot in one campaign, against the robot's baseline.

    Attributes
    ----------
    robot_id, parameter
        The robot and the fleet-table column of the parameter.
    baseline, campaign, date
        Baseline campaign, the campaign compared and its date (ISO 8601).
    baseline_value, baseline_std, value, std
        Estimates and their standard deviations, in the parameter's unit.
    change
        ``value − baseline_value``; ``change_percent`` relative to ``|baseline_value|``.
    z
        Change in combined standard deviations (±inf when both σ are zero and it changed).
    flagged
        ``|z| > threshold``.
    """

    robot_id: str
    parameter: str
    baseline: str
    campaign: str
    date: str
    baseline_value: float
    baseline_std: float
    value: float
    std: float
    change: float
    change_percent: float | None
    z: float
    flagged: bool


@dataclass
class DriftReport:
    """Every comparison, the threshold, each robot's baseline, and what could not be compared."""

    threshold: float
    rows: list[Drift]
    baselines: dict[str, str]
    notes: list[str] = field(default_factory=list)

    @property
    def flagged(self) -> list[Drift]:
        return [d for d in self.rows if d.flagged]


def _num(x: Any) -> float | None:
    if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
        return None
    return float(x)


def compute_drift(
    rows: Sequence[dict[str, Any]], threshold: float, baseline: str | None = None
) -> DriftReport:
    """Compare each robot's campaigns with its baseline (module docstring).

    Parameters
    ----------
    rows
        Fleet-table rows (:func:`drivegain.fleet.table.fleet_rows`).
    threshold
        Flag beyond this many combined standard deviations.
    baseline
        Baseline campaign name for every robot (default: each robot's earliest successful
        campaign). A robot without it is not compared (a note says so).
    """
    params = [p for p in parameters(rows) if not p.startswith(NOT_COMPARED)]
    by_robot: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        if r["status"] == "ok":
            by_robot.setdefault(r["robot_id"], []).append(r)
    out: list[Drift] = []
    baselines: dict[str, str] = {}
    notes: list[str] = []
    for rid, runs in sorted(by_robot.items()):
        runs = sorted(runs, key=lambda r: (r["date"], r["campaign"]))
        base = (
            runs[0]
            if baseline is None
            else next((r for r in runs if r["campaign"] == baseline), None)
        )
        if base is None:
            notes.append(f"{rid}: no successful identification in baseline campaign {baseline}")
            continue
        baselines[rid] = base["campaign"]
        for r in runs:
            if r is base:
                continue
            for p in params:
                v0, s0 = _num(base.get(p)), _num(base.get(p + STD))
                v1, s1 = _num(r.get(p)), _num(r.get(p + STD))
                if v0 is None or v1 is None or s0 is None or s1 is None:
                    continue
                change = v1 - v0
                sigma = math.hypot(s0, s1)
                if sigma > 0:
                    z = change / sigma
                else:
                    z = 0.0 if change == 0 else math.copysign(math.inf, change)
                out.append(
                    Drift(
                        robot_id=rid,
                        parameter=p,
                        baseline=base["campaign"],
                        campaign=r["campaign"],
                        date=r["date"],
                        baseline_value=v0,
                        baseline_std=s0,
                        value=v1,
                        std=s1,
                        change=change,
                        change_percent=100 * change / abs(v0) if v0 != 0 else None,
                        z=z,
                        flagged=abs(z) > threshold,
                    )
                )
    return DriftReport(threshold=threshold, rows=out, baselines=baselines, notes=notes)


def plot_robot(report: DriftReport, robot_id: str) -> bytes:
    """PNG of a robot's drift: z of every parameter per campaign, flagged bars in red.

    The z axis is symmetric-logarithmic beyond the threshold, so a change of hundreds of σ and
    the noise of unchanged parameters show on one plot. Uses matplotlib's object API (Agg), no
    pyplot state: safe in any thread.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = [d for d in report.rows if d.robot_id == robot_id]
    params = list(dict.fromkeys(d.parameter for d in rows))
    campaigns = list(dict.fromkeys(d.campaign for d in rows))
    fig = Figure(figsize=(8, max(3.0, 0.22 * len(params) + 1.5)))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    height = 0.8 / max(1, len(campaigns))
    for k, c in enumerate(campaigns):
        zs = {d.parameter: d for d in rows if d.campaign == c}
        ys = [i + (k - (len(campaigns) - 1) / 2) * height for i in range(len(params))]
        vals = [zs[p].z if p in zs and math.isfinite(zs[p].z) else 0.0 for p in params]
        colours = ["tab:red" if p in zs and zs[p].flagged else f"C{k}" for p in params]
        ax.barh(
            ys, vals, height=height, color=colours, label=f"{c} ({next(iter(zs.values())).date})"
        )
        for y, p in zip(ys, params, strict=True):
            if p in zs and zs[p].flagged:
                pct = zs[p].change_percent
                text = f" {zs[p].z:+.3g}σ" + ("" if pct is None else f" ({pct:+.2g} %)")
                ax.text(zs[p].z, y, text, va="center", fontsize=7)
    thr = report.threshold
    for x in (-thr, thr):
        ax.axvline(x, color="k", lw=0.8, ls="--")
    ax.set_xscale("symlog", linthresh=thr)
    finite = [d.z for d in rows if math.isfinite(d.z)] or [0.0]
    # Room for the labels of the flagged bars (a decade beyond the largest on a log axis).
    ax.set_xlim(min(-2 * thr, 10 * min(finite)), max(2 * thr, 10 * max(finite)))
    ax.set_yticks(range(len(params)), params, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel(f"change against baseline {report.baselines.get(robot_id, '')}, σ (combined)")
    ax.set_title(f"{robot_id}: parameter drift (flagged beyond ±{thr:g}σ, red)")
    ax.grid(alpha=0.3, axis="x")
    if campaigns:
        ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def drift_json(report: DriftReport) -> dict[str, Any]:
    """``drift.json``: threshold, baselines, flagged changes, notes."""
    return {
        "format_version": 1,
        "threshold_sigma": report.threshold,
        "baselines": report.baselines,
        "compared": len(report.rows),
        "flagged": [asdict(d) for d in report.flagged],
        "notes": report.notes,
    }


@dataclass
class FleetOutputs:
    """What :func:`write_fleet_outputs` wrote and found."""

    rows: list[dict[str, Any]]
    drift: DriftReport
    files: list[str]


def write_fleet_outputs(
    out: str, threshold: float, baseline: str | None = None, plots: bool = True
) -> FleetOutputs:
    """Fleet table and drift report of every result stored in ``out`` (module docstring)."""
    rows = fleet_rows(load_results(out))
    files = write_table(to_arrow(rows), out, "fleet") if rows else []
    report = compute_drift(rows, threshold, baseline)
    if report.rows:
        drift_rows = [asdict(d) for d in report.rows]
        for d in drift_rows:  # ±inf is not CSV-friendly: keep the sign with a huge finite value
            if not math.isfinite(d["z"]):
                d["z"] = math.copysign(1e300, d["z"])
        files += write_table(to_arrow(drift_rows), out, "drift")
    location = storage.join(out, "drift.json")
    storage.write_atomic(location, (json.dumps(drift_json(report), indent=1) + "\n").encode())
    files.append(location)
    if plots:
        for rid in sorted({d.robot_id for d in report.rows}):
            location = storage.join(out, "drift", f"{rid}.png")
            storage.write_atomic(location, plot_robot(report, rid))
            files.append(location)
    return FleetOutputs(rows=rows, drift=report, files=files)
