"""``identify --consistent``: run the consistent fit after the procedure and report it beside
the unconstrained one (the ``consistent`` section of ``report.json``, contracts §5, and a
Markdown section).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivegain.config import load_truth, resource_path
from drivegain.config.robot import Robot
from drivegain.dynamics.params import N_PER_JOINT, PER_JOINT, standard_names, truth_vector
from drivegain.identify.consistent import (
    DEFAULT_PRIOR_WEIGHT,
    GAIN_MODES,
    ConsistentCV,
    ConsistentFit,
    cross_validate_consistent,
    fit_consistent,
    pseudo_inertia_eigenvalues,
)
from drivegain.identify.procedure import Problem, ProcedureResult
from drivegain.identify.report import PAYLOAD_KEYS

#: A priori (CAD-like) parameters shipped for known robots (sim-truth TOML format).
SHIPPED_PRIOR = {"Staubli TX-40": "sim/tx40-truth.toml"}


@dataclass(frozen=True)
class ConsistentRequest:
    """Options of ``identify --consistent``.

    Attributes
    ----------
    prior
        A priori standard parameters (sim-truth TOML), or None for the shipped ones of a known
        robot (zeros otherwise).
    prior_weight
        λ, weight of the pull towards the a priori parameters.
    gains
        One of :data:`~drivegain.identify.consistent.GAIN_MODES`.
    solver
        cvxpy solver name.
    """

    prior: Path | None = None
    prior_weight: float = DEFAULT_PRIOR_WEIGHT
    gains: str = "fixed"
    solver: str = "CLARABEL"


def request_from_args(args: Any) -> ConsistentRequest | None:
    """The request of the command line's options (None without ``--consistent``)."""
    if not getattr(args, "consistent", False):
        return None
    weight = getattr(args, "prior_weight", None)
    return ConsistentRequest(
        prior=getattr(args, "prior", None),
        prior_weight=DEFAULT_PRIOR_WEIGHT if weight is None else float(weight),
        gains=getattr(args, "consistent_gains", None) or "fixed",
    )


def load_prior(robot: Robot, path: Path | None) -> tuple[np.ndarray | None, str]:
    """A priori standard parameters and where they came from (None, "none" when unknown)."""
    if path is None:
        shipped = SHIPPED_PRIOR.get(robot.name)
        if shipped is None:
            return None, "none"
        path = resource_path(shipped)
    return truth_vector(robot, load_truth(path, robot.n)), str(path)


@dataclass(frozen=True)
class ConsistentOutcome:
    """The consistent fit on all data and its held-out quality."""

    fit: ConsistentFit
    cv: ConsistentCV
    prior_source: str
    prior_weight: float


def run_consistent(
    req: ConsistentRequest, problem: Problem, result: ProcedureResult
) -> ConsistentOutcome:
    """The consistent fit with the final case's gains and weights, and its cross-validation."""
    robot = problem.robot
    bp = problem.bases[result.friction]
    designs = [result.designs[k] for k in ("unloaded", "loaded") if k in result.designs]
    prior, source = load_prior(robot, req.prior)
    final = result.final
    kw: dict[str, Any] = {
        "prior": prior,
        "prior_weight": req.prior_weight,
        "gain_mode": req.gains,
        "solver": req.solver,
    }
    gains = final.gains if req.gains == "fixed" else result.apriori
    fit = fit_consistent(designs, bp, robot, gains, final.sigma_joint, **kw)
    cv = cross_validate_consistent(designs, bp, robot, gains, result.cv.fraction, **kw)
    return ConsistentOutcome(fit=fit, cv=cv, prior_source=source, prior_weight=req.prior_weight)


def _num(x: float | None) -> float | None:
    if x is None:
        return None
    v = float(x)
    return v if math.isfinite(v) else None


def links_json(robot: Robot, chi: np.ndarray) -> list[dict[str, Any]]:
    """Per link: its 14 standard parameters, centre of mass (m) and pseudo-inertia eigenvalues."""
    out = []
    for j, name in enumerate(robot.joint_names):
        block = chi[N_PER_JOINT * j : N_PER_JOINT * (j + 1)]
        row: dict[str, Any] = {"joint": name, "link": j + 1}
        row |= {k: _num(v) for k, v in zip(PER_JOINT, block, strict=True)}
        m = float(block[9])
        row["com"] = [_num(c / m) for c in block[6:9]] if m > 0 else None
        row["pseudo_inertia_eigenvalues"] = [
            _num(e) for e in pseudo_inertia_eigenvalues(block[:10])
        ]
        out.append(row)
    return out


def consistent_json(
    out: ConsistentOutcome, problem: Problem, result: ProcedureResult
) -> dict[str, Any]:
    """The ``consistent`` section of ``report.json`` (additive, contracts §5)."""
    robot = problem.robot
    bp = problem.bases[result.friction]
    fit, cv, final = out.fit, out.cv, result.final
    names = standard_names(robot)
    couplings = []
    for k, c in enumerate(robot.couplings):
        off = N_PER_JOINT * robot.n + 2 * k
        couplings.append(
            {
                "motor": c.motor + 1,
                "joint": c.joint + 1,
                "fvm": _num(fit.standard[off]),
                "fcm": _num(fit.standard[off + 1]),
            }
        )
    doc: dict[str, Any] = {
        "solver": {
            "name": fit.solver,
            "status": fit.status,
            "solve_time_s": _num(fit.solve_time_s),
            "setup_time_s": _num(fit.setup_time_s),
        },
        "prior": {"source": out.prior_source, "weight": out.prior_weight},
        "friction": result.friction.value,
        "gains": {
            "mode": fit.gain_mode,
            "values": [_num(g) for g in fit.gains],
            "active": [c.name for c in fit.active if c.kind == "gain_sign"],
        },
        "residual": {
            "norm": _num(fit.residual_norm),
            "relative": _num(fit.relative_error),
            "unconstrained_relative": _num(final.relative_error),
            "objective_ratio": _num(fit.objective_ratio),
        },
        "r2": [_num(v) for v in fit.r2],
        "unconstrained_r2": [_num(v) for v in final.r2],
        "cross_validation": {
            "held_out_fraction": result.cv.fraction,
            "relative": _num(cv.relative_error),
            "unconstrained_relative": _num(result.cv.relative_error),
            "r2": [_num(v) for v in cv.r2],
            "unconstrained_r2": [_num(v) for v in result.cv.r2],
        },
        "constraints": [
            {"name": c.name, "kind": c.kind, "value": _num(c.value), "active": c.active}
            for c in fit.constraints
        ],
        "active": [c.name for c in fit.active],
        "standard_names": names,
        "standard": [_num(v) for v in fit.standard],
        "links": links_json(robot, fit.standard),
        "couplings": couplings,
        "base_parameters": [
            {
                "name": nm,
                "expression": ex,
                "value": _num(v),
                "unconstrained": _num(u),
                "unconstrained_std": _num(s),
            }
            for nm, ex, v, u, s in zip(
                bp.names, bp.expressions, fit.base, final.base, final.base_std, strict=True
            )
        ],
    }
    if fit.payloads:
        p = fit.payloads[0]
        doc["payload"] = {k: _num(p[i]) for i, k in enumerate(PAYLOAD_KEYS)}
        doc["payload"]["pseudo_inertia_eigenvalues"] = [
            _num(e) for e in pseudo_inertia_eigenvalues(p)
        ]
    return doc


def summary_line(doc: dict[str, Any]) -> str:
    """One line for the command's summary: consistent against unconstrained fit."""
    res, cv = doc["residual"], doc["cross_validation"]
    return (
        f"consistent fit ({doc['solver']['name']}, {_g(doc['solver']['solve_time_s'], 2)} s): "
        f"relative error norm {_g(res['relative'])} (unconstrained "
        f"{_g(res['unconstrained_relative'])}), held-out {_g(cv['relative'])} (unconstrained "
        f"{_g(cv['unconstrained_relative'])}); active: {', '.join(doc['active']) or 'none'}"
    )


def _g(x: float | None, digits: int = 4) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{digits}g}"


def consistent_markdown(doc: dict[str, Any], robot: Robot) -> str:
    """The Markdown section of the consistent fit."""
    res, cv = doc["residual"], doc["cross_validation"]
    lines = [
        "",
        "## Physically consistent fit (`--consistent`)",
        "",
        "Least squares of the base parameters over real rigid bodies (pseudo-inertia ⪰ 0 for "
        "every link and the payload, Ia, Fv, Fc ≥ 0), solved as an SDP "
        f"({doc['solver']['name']}, {doc['solver']['status']}, "
        f"{_g(doc['solver']['solve_time_s'], 3)} s); a priori parameters "
        f"`{Path(doc['prior']['source']).name}` with weight {doc['prior']['weight']:g}; gains "
        f"{doc['gains']['mode']}.",
        "",
        "| fit | ‖ρ‖/‖Y‖ | held-out ‖ρ‖/‖Y‖ | "
        + " | ".join(f"R² {n}" for n in robot.joint_names)
        + " |",
        "|---|---|---|" + "---|" * robot.n,
    ]
    for label, rel, hold, r2 in (
        (
            "unconstrained",
            res["unconstrained_relative"],
            cv["unconstrained_relative"],
            doc["unconstrained_r2"],
        ),
        ("consistent", res["relative"], cv["relative"], doc["r2"]),
    ):
        lines.append(
            f"| {label} | {_g(rel)} | {_g(hold)} | " + " | ".join(_g(v) for v in r2) + " |"
        )
    active = doc["active"]
    lines += ["", f"Active constraints: {', '.join(active) if active else 'none'}."]
    if doc["gains"]["active"]:
        lines.append(f"Gain sign constraints active: {', '.join(doc['gains']['active'])}.")
    lines += [
        "",
        "| link | M kg | MX | MY | MZ | XX | XY | XZ | YY | YZ | ZZ | Ia | Fv | Fc |",
        "|---|" + "---|" * 13,
    ]
    for row in doc["links"]:
        keys = ("M", "MX", "MY", "MZ", "XX", "XY", "XZ", "YY", "YZ", "ZZ", "Ia", "Fv", "Fc")
        lines.append(f"| {row['joint']} | " + " | ".join(_g(row[k]) for k in keys) + " |")
    lines += [
        "",
        "Base parameters (regrouping shown): consistent B·χ and unconstrained.",
        "",
        "| base parameter | consistent | unconstrained | 2σ |",
        "|---|---|---|---|",
    ]
    for b in doc["base_parameters"]:
        s = b["unconstrained_std"]
        lines.append(
            f"| `{b['expression']}` | {_g(b['value'])} | {_g(b['unconstrained'])} | "
            f"{_g(None if s is None else 2 * s, 3)} |"
        )
    return "\n".join(lines) + "\n"


__all__ = ["GAIN_MODES", "ConsistentRequest", "consistent_json", "consistent_markdown"]
