"""Identification reports: ``report.json`` (contracts §5) and a Markdown report with the paper's
tables (Table 2: payload parameters, Table 3: drive gains, Table 4: error norms, Table 5: the
validation payload) and the method's diagnostics.

Standard deviations in ``report.json`` are one σ; the Markdown tables print 2σ and %σ as the
paper does.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from drivegain.config.payload import PAYLOAD_PARAMS
from drivegain.config.robot import Robot
from drivegain.identify.cases import CaseResult, PayloadEstimate
from drivegain.identify.gains import DEFAULT_ALPHA_GRID
from drivegain.identify.procedure import ProcedureResult
from drivegain.identify.report_ml import estimator_name, ml_json, ml_lines
from drivegain.identify.reportfmt import PAYLOAD_KEYS
from drivegain.identify.reportfmt import json_num as _num
from drivegain.identify.reportfmt import short as _g
from drivegain.identify.units import GAIN_UNIT, parameter_unit

FORMAT_VERSION = 1
#: Held-out residual norms closer than this fraction do not tell two friction forms apart.
FORM_MARGIN = 0.01


@dataclass(frozen=True)
class RunInfo:
    """What the report says about one input run."""

    label: str
    source: str
    raw_samples: int
    samples: int
    rate_hz: float
    decimated_rate_hz: float
    payload: str
    filter: Mapping[str, Any] | None
    notes: list[str] = field(default_factory=list)
    time_base: Mapping[str, Any] | None = None
    current: str = "reference"


def _rsd(value: float, std: float | None) -> float | None:
    if std is None or value == 0.0:
        return None
    return _num(100.0 * std / abs(value))


def _payload_json(p: PayloadEstimate) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for i, key in enumerate(PAYLOAD_KEYS):
        out[key] = {
            "value": _num(p.values[i]),
            "std": _num(p.std[i]),
            "rel_std_percent": _rsd(float(p.values[i]), float(p.std[i])),
            "nominal": _num(p.nominal[i]),
        }
    out["name"] = p.name
    out["known_in_wtls"] = [PAYLOAD_KEYS[PAYLOAD_PARAMS.index(k)] for k in p.known]
    return out


def _base_json(case: CaseResult, expressions: Mapping[str, str]) -> list[dict[str, Any]]:
    return [
        {
            "name": name,
            "value": _num(v),
            "std": _num(s),
            "rel_std_percent": _rsd(float(v), float(s)),
            "expression": expressions.get(name, name),
            # eq. (10)'s white-noise σ, beside the HAC one in "std" (docs/model.md)
            "wls_std": _num(ws),
        }
        for name, v, s, ws in zip(
            case.base_names, case.base, case.base_std, case.wls.std[: case.base.size], strict=True
        )
    ]


def _case_json(case: CaseResult, robot: Robot, expressions: Mapping[str, str]) -> dict[str, Any]:
    return {
        "gains": [_num(g) for g in case.gains],
        "payloads": [_payload_json(p) for p in case.payloads],
        "base_parameters": _base_json(case, expressions),
        "residual": {
            "norm": _num(case.residual_norm),
            "relative": _num(case.relative_error),
            "sigma": _num(case.sigma_rho),
        },
        "joints": [
            {
                "joint": name,
                "r2": _num(case.r2[j]),
                "relative": _num(case.joint_relative[j]),
                "sigma_weight": _num(case.sigma_joint[j]),
            }
            for j, name in enumerate(robot.joint_names)
        ],
        "rows": case.rows,
        "left_out_entries": case.left_out,
        "covariance": str(case.covariance),
        "covariance_lag_samples": case.lag,
    }


def report_json(
    result: ProcedureResult,
    robot: Robot,
    runs: Sequence[RunInfo],
    expressions: Mapping[str, str],
) -> dict[str, Any]:
    """The ``report.json`` document (contracts §5 plus extra fields).

    Parameters
    ----------
    result
        The procedure's result.
    robot
        The robot description (joint names).
    runs
        The input runs, for provenance.
    expressions
        Base parameter name -> regrouping expression.
    """
    final = result.final
    gains = []
    for j, name in enumerate(robot.joint_names):
        std = None if result.gains_std is None else float(result.gains_std[j])
        gains.append(
            {
                "joint": name,
                "value": _num(result.gains[j]),
                "std": _num(std),
                "rel_std_percent": _rsd(float(result.gains[j]), std),
                "apriori": _num(result.apriori[j]),
            }
        )
    doc: dict[str, Any] = {"format_version": FORMAT_VERSION, "gains": gains}
    if final.payloads:
        doc["payload"] = _payload_json(final.payloads[0])
    doc["base_parameters"] = _base_json(final, expressions)
    doc["residual"] = {
        "norm": _num(final.residual_norm),
        "relative": _num(final.relative_error),
        "sigma": _num(final.sigma_rho),
    }
    w = result.wtls
    doc["method"] = {
        "estimator": estimator_name(w),
        "alpha": None if w is None or w.fit is None else _num(w.fit.alpha),
        "samples": int(sum(result.samples.values())),
        "gains_source": result.gains_source,
        "parameters_estimator": "IDIM-WLS",
        "friction": result.friction.value,
        "case": final.name,
    }
    doc["runs"] = [
        {
            "label": r.label,
            "source": r.source,
            "raw_samples": r.raw_samples,
            "samples": r.samples,
            "rate_hz": _num(r.rate_hz),
            "decimated_rate_hz": _num(r.decimated_rate_hz),
            "payload": r.payload,
            "filter": dict(r.filter) if r.filter is not None else None,
            "notes": list(r.notes),
            "time_base": None if r.time_base is None else dict(r.time_base),
            "current": r.current,
        }
        for r in runs
    ]
    cases = {result.case1.name: _case_json(result.case1, robot, expressions)}
    if result.case2 is not None:
        cases["case2"] = _case_json(result.case2, robot, expressions)
    doc["cases"] = cases
    if w is not None and w.ml is not None:
        doc["ml"] = ml_json(w, robot)
    if w is not None and w.fit is not None and w.sigma_initial is not None:
        tls = w.fit.tls
        doc["wtls"] = {
            "alpha": _num(w.fit.alpha),
            "alpha_curve": [[_num(a), _num(e)] for a, e in w.alpha_curve],
            "alpha_failures": [{"alpha": _num(a), "error": msg} for a, msg in w.failures],
            "alpha_curve_flatness": _num(w.alpha_flatness),
            "relative_error": _num(w.fit.relative_error),
            "relative_error_unweighted": _num(w.fit.relative_error_unweighted),
            "singular_values": [_num(s) for s in tls.singular_values],
            "singular_value_gap": _num(tls.gap),
            "delta_component": _num(tls.delta_component),
            "theta_smallest_singular_value": _num(tls.theta_smin),
            "sigma_initial": [_num(s) for s in w.sigma_initial],
            "sigma": [_num(s) for s in w.fit.sigma],
            "iterations": w.fit.iterations,
            "converged": w.fit.converged,
            "covariance": "sandwich (cluster scores)",
            "covariance_window_samples": w.block,
            "covariance_clusters": w.clusters,
            "column_weights": [_num(c) for c in w.fit.column_weights],
            "payload_unknown": {
                PAYLOAD_KEYS[PAYLOAD_PARAMS.index(p)]: {"value": _num(v), "std": _num(s)}
                for p, v, s in zip(w.payload_names, w.payload_unknown, w.payload_std, strict=True)
            },
        }
    if result.validation:
        doc["validation"] = {
            name: _payload_json(case.payloads[0])
            | {"relative_error": _num(case.relative_error), "gains": [_num(g) for g in case.gains]}
            for name, case in result.validation.items()
        }
    cv = result.cv
    doc["cross_validation"] = {
        "held_out_fraction": cv.fraction,
        "relative": _num(cv.relative_error),
        "train_relative": _num(cv.train_relative_error),
        "joints": [
            {"joint": nm, "r2": _num(cv.r2[j]), "relative": _num(cv.joint_relative[j])}
            for j, nm in enumerate(robot.joint_names)
        ],
    }
    better = result.better_form()
    doc["friction_forms"] = {
        "compared": {
            f.value: {
                "relative": _num(ff.case.relative_error),
                "cv_relative": _num(ff.cv.relative_error),
                "r2": [_num(v) for v in ff.case.r2],
                "cv_r2": [_num(v) for v in ff.cv.r2],
            }
            for f, ff in result.forms.items()
        },
        "better": None if better is None else better.value,
        "held_out_margin": _num(result.form_margin()),
        "distinguishable": bool((result.form_margin() or 0.0) >= FORM_MARGIN),
    }
    doc["checks"] = [
        {"name": c.name, "value": _num(c.value), "std": _num(c.std), "ok": c.ok, "note": c.note}
        for c in result.checks
    ]
    doc["warnings"] = list(result.warnings)
    return doc


# --------------------------------------------------------------------------------------------
# Markdown


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def _payload_rows(cases: Sequence[PayloadEstimate]) -> list[list[str]]:
    rows = []
    for i, p in enumerate(PAYLOAD_PARAMS):
        name = "M" if p == "M" else p
        row = [f"{name}_L", parameter_unit(p), _g(float(cases[0].nominal[i]))]
        for c in cases:
            row += [
                _g(float(c.values[i])),
                _g(2 * float(c.std[i]), 3),
                _g(_rsd(float(c.values[i]), float(c.std[i])), 2),
            ]
        rows.append(row)
    return rows


def markdown_report(
    doc: Mapping[str, Any],
    result: ProcedureResult,
    robot: Robot,
    runs: Sequence[RunInfo],
    plots: Mapping[str, str],
) -> str:
    """The human report (Markdown), with the paper's tables and the plots' file names."""
    lines = [f"# Drive gain identification: {robot.name}", ""]
    m = doc["method"]
    lines += [
        f"- Gains: **{m['estimator'] if result.wtls else 'not identified'}**"
        f" ({'identified' if result.wtls else 'source: ' + result.gains_source});"
        " parameters by IDIM-WLS"
        + (f"; coupled-wrist friction form `{m['friction']}`." if robot.couplings else "."),
        f"- Samples used (after decimation): {m['samples']}"
        + (f"; α = {_g(m['alpha'])}" if m["alpha"] is not None else "")
        + ".",
        "- " + _cases_sentence(result),
        "- Uncertainties: a column or value marked 2σ is twice the standard deviation (about "
        "95 % for Gaussian errors); %σ = 100·σ/|value| is one σ relative to the value, as in "
        "the paper's tables.",
        "",
        "## Runs",
        "",
    ]
    lines += _table(
        ["run", "file", "samples", "rate Hz", "kept", "kept rate Hz", "payload", "filter"],
        [
            [
                r.label,
                f"`{r.source}`",
                str(r.raw_samples),
                _g(r.rate_hz),
                str(r.samples),
                _g(r.decimated_rate_hz),
                r.payload,
                (
                    f"Butterworth {_g(r.filter['cutoff_hz'])} Hz order {r.filter['order']},"
                    f" decimation {r.filter['decimate']}, trim {r.filter['trim']}"
                )
                if r.filter
                else "exact derivatives",
            ]
            for r in runs
        ],
    )
    for r in runs:
        lines += [f"- {r.label}: {note}" for note in r.notes]
    if result.warnings:
        lines += ["", "## Warnings", ""]
        lines += ["A value written ± x in a warning is 2σ, as in the tables; %σ is 1σ.", ""]
        lines += [f"- {w}" for w in result.warnings]

    lines += ["", "## Drive gains (Table 3)", ""]
    header = ["", *robot.joint_names]
    rows = [[f"a priori g ({GAIN_UNIT})", *[_g(float(g)) for g in result.apriori]]]
    label = "identified g" if result.wtls else f"used g ({result.gains_source})"
    rows.append([f"{label} ({GAIN_UNIT})", *[_g(float(g)) for g in result.gains]])
    if result.gains_std is not None:
        rows.append([f"2σ ({GAIN_UNIT})", *[_g(2 * float(s), 3) for s in result.gains_std]])
        rows.append(
            [
                "%σ",
                *[
                    _g(_rsd(float(g), float(s)), 2)
                    for g, s in zip(result.gains, result.gains_std, strict=True)
                ],
            ]
        )
        rows.append(
            [
                "change vs a priori %",
                *[
                    _g(100.0 * (float(g) / float(a) - 1.0), 3)
                    for g, a in zip(result.gains, result.apriori, strict=True)
                ],
            ]
        )
    lines += _table(header, rows)

    fitted = [result.case1] + ([result.case2] if result.case2 is not None else [])
    if result.final.payloads:
        lines += ["", "## Payload parameters (Table 2)", ""]
        head = ["par.", "unit", "nominal"]
        for c in fitted:
            head += [f"{c.name} value", "2σ", "%σ"]
        lines += _table(head, _payload_rows([c.payloads[0] for c in fitted]))
        lines += ["", "Inertia at the frame origin of the link the payload is fixed to."]

    lines += ["", "## Quality of identification (Table 4)", ""]
    rows = []
    for c in fitted:
        rows.append(
            [c.name, _g(c.residual_norm), _g(c.relative_error), _g(c.sigma_rho), str(c.rows)]
        )
    lines += _table(["case", "‖ρ‖ N·m", "‖ρ‖/‖Y‖", "σ̂_ρ N·m", "equations"], rows)
    for c in fitted:
        if c.left_out:
            lines += [
                "",
                f"{c.name} left {c.left_out} entries (sample and joint) out of its fit: those "
                "near reversals of the drives whose entries there the gains' error model finds "
                'misfit (docs/model.md, "Case 2 without the misfit reversals"). Its equations '
                "are those it fitted, its norms count every entry.",
            ]
    fin = result.final
    lines += ["", f"Per joint ({fin.name}):", ""]
    lines += _table(
        ["joint", "R²", "‖ρ_j‖/‖Y_j‖", "σ_j N·m", "held-out R²", "held-out ‖ρ_j‖/‖Y_j‖"],
        [
            [
                nm,
                _g(float(fin.r2[j])),
                _g(float(fin.joint_relative[j])),
                _g(float(fin.sigma_joint[j]), 3),
                _g(float(result.cv.r2[j])),
                _g(float(result.cv.joint_relative[j])),
            ]
            for j, nm in enumerate(robot.joint_names)
        ],
    )
    cv = result.cv
    lines += [
        "",
        f"Cross-validation: fitted on the first {100 * (1 - cv.fraction):.0f} % of every run, "
        f"the last {100 * cv.fraction:.0f} % held out: relative error norm "
        f"{_g(cv.relative_error)} on the held-out samples ({_g(cv.train_relative_error)} on "
        "the fitted ones).",
    ]

    if result.validation:
        lines += ["", "## Validation payload (Table 5)", ""]
        vcases = list(result.validation.values())
        head = ["par.", "unit", "nominal"]
        for c in vcases:
            head += [f"{c.name} value", "2σ", "%σ"]
        lines += _table(head, _payload_rows([c.payloads[0] for c in vcases]))

    if len(result.forms) > 1:
        lines += ["", "## Coupled-wrist friction forms", ""]
        lines += _table(
            ["form", "‖ρ‖/‖Y‖", "held-out ‖ρ‖/‖Y‖", "R² joint 5", "R² joint 6"],
            [
                [
                    f.value,
                    _g(ff.case.relative_error),
                    _g(ff.cv.relative_error),
                    _g(float(ff.case.r2[4])) if ff.case.r2.size > 5 else "–",
                    _g(float(ff.case.r2[5])) if ff.case.r2.size > 5 else "–",
                ]
                for f, ff in result.forms.items()
            ],
        )
        better = result.better_form()
        margin = result.form_margin()
        if better is not None and margin is not None:
            verdict = (
                "a clear difference"
                if margin >= FORM_MARGIN
                else "not a meaningful difference: the data do not tell the forms apart"
            )
            lines += [
                "",
                f"Lower held-out residual: `{better.value}`, by {100 * margin:.2g} % ({verdict}).",
            ]

    if result.checks:
        lines += ["", "## Physical plausibility", ""]
        lines += _table(
            ["parameter", "value", "2σ", "unit", "status"],
            [
                [
                    c.name,
                    _g(c.value),
                    _g(2 * c.std, 3),
                    parameter_unit(c.name),
                    "ok" if c.ok else f"**flagged**: {c.note}",
                ]
                for c in result.checks
            ],
        )

    if result.wtls is not None and result.wtls.ml is not None:
        lines += ml_lines(result.wtls, robot)
    if result.wtls is not None and result.wtls.fit is not None:  # the paper's WTLS was run
        w = result.wtls
        assert w.fit is not None and w.sigma_initial is not None  # (narrowing, for mypy)
        t = w.fit.tls
        lines += ["", "## IDIM-WTLS diagnostics", ""]
        lines += [
            _alpha_sentence(result, plots)
            + (
                ""
                if w.alpha_flatness is None
                else f"; the norm varies by {_g(w.alpha_flatness, 2)} (relative) over the "
                "curve" + (": flat, α hardly matters" if w.alpha_flatness < 1e-4 else "")
            )
            + ".",
            *[f"- α = {_g(a)} failed: {msg}" for a, msg in w.failures],
            f"- Two smallest singular values: {_g(float(t.singular_values[-2]))}, "
            f"{_g(float(t.singular_values[-1]))} (ratio {_g(t.gap)}); |δ| in the singular "
            f"vector {_g(t.delta_component)}. The gains come from the right singular vector of "
            "the smallest one; the larger the gap (ratio) to the next, the better that vector, "
            "and so the gains, are determined by the data (a ratio near 1 means two directions "
            "fit almost equally well).",
            f"- σ_j (N·m) from per-joint OLS with the a priori gains: "
            f"{', '.join(_g(float(s), 3) for s in w.sigma_initial)}; after "
            f"{w.fit.iterations} WTLS iterations: "
            f"{', '.join(_g(float(s), 3) for s in w.fit.sigma)}.",
            f"- V columns weighted by α·c_m with c = "
            f"{', '.join(_g(float(c) / w.fit.alpha, 3) for c in w.fit.column_weights)} "
            "(each drive's current noise made equal, so that the TLS noise is isotropic).",
            f"- Gain standard deviations: first-order sandwich covariance of the TLS estimating "
            f"equation, scores summed over {w.clusters} clusters (windows of {w.block} samples"
            f", gathered over the excitation's periods when it is periodic).",
        ]

    lines += ["", "## Base parameters", ""]
    lines += ["Units for revolute joints; a regrouped parameter has its leading term's.", ""]
    lines += _table(
        ["parameter", "value", "2σ", "%σ", "unit", "expression"],
        [
            [
                b["name"],
                _g(b["value"]),
                _g(None if b["std"] is None else 2 * b["std"], 3),
                _g(b["rel_std_percent"], 3),
                parameter_unit(b["name"]),
                b["expression"],
            ]
            for b in doc["base_parameters"]
        ],
    )
    if plots:
        lines += ["", "## Plots", ""]
        for name, path in plots.items():
            lines += [f"![{name}]({path})", "", _caption(name, result), ""]
    return "\n".join(lines) + "\n"


def _cases_sentence(result: ProcedureResult) -> str:
    """What the cases of the tables are, in one sentence (their first appearance)."""
    if result.case2 is not None:
        return (
            f"Cases: Case 1 (`{result.case1.name}`) fits the dynamic and payload parameters by "
            "IDIM-WLS with the a priori drive gains, Case 2 (`case2`) with the gains identified "
            "by IDIM-WTLS, so comparing them shows what identifying the gains changes."
        )
    return (
        f"Cases: one case (`{result.case1.name}`), the dynamic and payload parameters fitted by "
        f"IDIM-WLS with the gains used ({result.gains_source}); no Case 2, as the gains were "
        "not identified."
    )


def _alpha_sentence(result: ProcedureResult, plots: Mapping[str, str]) -> str:
    """How α was chosen, with the count split as the progress display shows it."""
    w = result.wtls
    assert w is not None and w.fit is not None
    if not w.alpha_curve:
        return f"- α = {_g(w.fit.alpha)} as given (not searched)"
    tried = [a for a, _ in w.alpha_curve]
    on_grid = sum(1 for a in tried if a in DEFAULT_ALPHA_GRID)
    split = (
        f"the {on_grid} of the log-spaced grid, then {len(tried) - on_grid} refined around the best"
        if 0 < on_grid < len(tried)
        else f"{len(tried)} values tried"
    )
    return (
        f"- α = {_g(w.fit.alpha)} chosen as the smallest weighted relative error norm over "
        f"{len(tried)} values ({split}; curve in `{plots.get('alpha', '–')}`)"
    )


def _caption(name: str, result: ProcedureResult) -> str:
    """One paragraph under a figure: what it shows and how to read it."""
    if name.startswith("torques_"):
        run = name.removeprefix("torques_")
        return (
            f"Run `{run}`: per joint, the torque measured through the drives (current "
            f"reference × {result.final.name} gains, V·g) and the one the identified model "
            "computes (W·χ), N·m; under each joint their difference on its own, finer scale "
            "with its RMS. A difference that looks like noise means the model explains the "
            "motion; a pattern in it is unmodelled dynamics."
        )
    if name == "alpha":
        return (
            "The α curve: α weighs the measured-current columns of the WTLS matrix against "
            "the model columns; the α with the smallest weighted relative error norm is used. "
            "A flat curve means the identified gains hardly depend on α."
        )
    if name == "singular_values":
        return (
            "Singular values of the weighted WTLS matrix. The gains come from the singular "
            "vector of the smallest one; the marked gap between the two smallest (their "
            "ratio) says how well the data single out that vector: the larger, the better."
        )
    return ""
