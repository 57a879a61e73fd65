"""The maximum-likelihood estimator's part of the report: JSON fields and Markdown lines."""

from __future__ import annotations

from typing import Any

from drivegain.config.payload import PAYLOAD_PARAMS
from drivegain.config.robot import Robot
from drivegain.identify.bootstrap import BootstrapSpread
from drivegain.identify.gains import Estimator, GainIdentification
from drivegain.identify.hac import MIN_PERIODS
from drivegain.identify.reportfmt import PAYLOAD_KEYS
from drivegain.identify.reportfmt import json_num as _num
from drivegain.identify.reportfmt import short as _g
from drivegain.identify.reversals import source_names


def estimator_name(w: GainIdentification | None) -> str:
    """``method.estimator`` of report.json: the gain estimator (IDIM-WLS when none ran)."""
    if w is None:
        return "IDIM-WLS"
    return "ML" if w.estimator is Estimator.ML else "IDIM-WTLS"


def ml_json(w: GainIdentification, robot: Robot) -> dict[str, Any]:
    """The maximum-likelihood estimator's noise model, covariance and errors-in-variables test."""
    ml, eiv = w.ml, w.eiv
    assert ml is not None and eiv is not None  # set together by the ML estimator
    velocities = source_names(robot)
    out = {
        "noise_std": [
            {"drive": name, "std": _num(s), "unit": "A"}
            for name, s in zip(robot.joint_names, ml.noise_std, strict=True)
        ],
        "noise_covariance": [[_num(v) for v in row] for row in ml.noise],
        "reversal_variance": [
            {"drive": name, "kappa": _num(k)}
            for name, k in zip(robot.joint_names, ml.kappa, strict=True)
        ],
        "reversal_coulomb": [
            {"velocity": velocities[int(k)], "value": _num(v), "std": _num(s), "unit": "N·m"}
            for k, v, s in zip(ml.coulomb_sources, ml.coulomb, ml.coulomb_std, strict=True)
        ],
        "rounds": ml.iterations,
        "converged": ml.converged,
        "start_gains": [_num(g) for g in ml.start_gains],
        "covariance": "error autocovariance, corrected for the fit",
        "covariance_lag_samples": ml.lag,
        "residual_lag1_autocorrelation": _num(ml.rho),
        "error_autocovariance": [_num(v) for v in ml.autocov.gamma],
        "gain_std_repeat_factor": None
        if ml.gain_repeat_scale is None
        else [_num(f) for f in ml.gain_repeat_scale],
        "payload_unknown": {
            PAYLOAD_KEYS[PAYLOAD_PARAMS.index(p)]: {"value": _num(v), "std": _num(s)}
            for p, v, s in zip(w.payload_names, w.payload_unknown, w.payload_std, strict=True)
        },
        "eiv_test": {
            "statistic": _num(eiv.statistic),
            "dof": eiv.dof,
            "p_value": _num(eiv.p_value),
            "ls_biased": eiv.biased,
            "ls_gains": [_num(g) for g in eiv.ls_gains],
            "ls_std": [_num(s) for s in eiv.ls_std],
        },
    }
    if w.bootstrap is not None:
        out["bootstrap"] = bootstrap_json(w.bootstrap, w.payload_names, robot)
    return out


def bootstrap_json(b: BootstrapSpread, payload_names: list[str], robot: Robot) -> dict[str, Any]:
    """``ml.bootstrap`` of report.json: the replicates asked for and their spread."""
    return {
        "method": "residual block bootstrap of the maximum-likelihood fit",
        "replicates": b.replicates,
        "failed": b.failed,
        "block_samples": b.block,
        "seed": b.seed,
        "gain_std": [
            {"drive": name, "std": _num(s), "unit": "N·m/A"}
            for name, s in zip(robot.joint_names, b.gain_std, strict=True)
        ],
        "payload_std": {
            PAYLOAD_KEYS[PAYLOAD_PARAMS.index(p)]: _num(s)
            for p, s in zip(payload_names, b.payload_std, strict=True)
        },
    }


def ml_lines(w: GainIdentification, robot: Robot) -> list[str]:
    """Markdown of the maximum-likelihood diagnostics."""
    ml, eiv = w.ml, w.eiv
    assert ml is not None and eiv is not None
    names = robot.joint_names
    velocities = source_names(robot)
    verdict = (
        f"**plain least squares is biased on these data** (p = {_g(eiv.p_value, 2)} < 0.01): "
        "the currents are noisy enough that treating them as exact regressors attenuates the "
        "gains"
        if eiv.biased
        else f"no evidence that plain least squares is biased here (p = {_g(eiv.p_value, 2)})"
    )
    return [
        "",
        "## Maximum-likelihood diagnostics",
        "",
        "- Gains, base and payload parameters by maximum likelihood in current units, with the "
        'noise covariance estimated from the data (docs/model.md, "Estimators"); no weight '
        "is chosen by hand.",
        "- Noise model (1σ of what the model leaves in each drive's current, A): "
        + ", ".join(f"{nm} {_g(float(s), 3)}" for nm, s in zip(names, ml.noise_std, strict=True))
        + ".",
        "- Entries near reversals of Coulomb friction: variance × (1 + κ·s), s the share of "
        "the filter window near a reversal of one of the drive's Coulomb terms; κ "
        + ", ".join(f"{nm} {_g(float(k), 3)}" for nm, k in zip(names, ml.kappa, strict=True))
        + ' (docs/model.md, "Reversals").',
        "- Coulomb friction near reversals, a coefficient of its own (N·m, added to the "
        "Coulomb term's while the velocity is within its reversal zone): "
        + (
            ", ".join(
                f"{velocities[int(k)]} {_g(float(v), 3)} ± {_g(float(s), 2)}"
                for k, v, s in zip(ml.coulomb_sources, ml.coulomb, ml.coulomb_std, strict=True)
            )
            or "none (no velocity has a reversal zone of its own)"
        )
        + ".",
        "- Standard deviations: from the whitened errors' autocovariance over "
        f"{ml.lag} decimated samples, corrected for the fit (long-run variance "
        f"{_g(ml.autocov.long_run, 3)} × that of white errors"
        + (", tapered to stay positive" if ml.autocov.tapered else "")
        + f"); {ml.iterations} rounds"
        + ("" if ml.converged else " (**did not settle**)")
        + ".",
        "- Errors repeating every period of the excitation: "
        + (
            f"not checked (no known period, or a run spans under {_g(MIN_PERIODS, 2)} of it)."
            if ml.gain_repeat_scale is None
            else "gain σ raised × "
            + ", ".join(
                f"{nm} {_g(float(f), 3)}" for nm, f in zip(names, ml.gain_repeat_scale, strict=True)
            )
            + ' (1: not raised; docs/model.md, "Errors that repeat every period").'
        ),
        f"- Errors-in-variables test (Durbin-Wu-Hausman, LS against ML): statistic "
        f"{_g(eiv.statistic, 3)} on {eiv.dof} degrees of freedom; " + verdict + ".",
        "- Plain LS gains (N·m/A, ± 2σ): "
        + ", ".join(
            f"{nm} {_g(float(g))} ± {_g(2 * float(s), 2)}"
            for nm, g, s in zip(names, eiv.ls_gains, eiv.ls_std, strict=True)
        )
        + ".",
        *_bootstrap_lines(w, names),
    ]


def _bootstrap_lines(w: GainIdentification, names: list[str]) -> list[str]:
    """The bootstrap σ of the gains beside the reported one, when it was asked for."""
    b = w.bootstrap
    if b is None:
        return []
    ratio = b.gain_std / w.std
    return [
        f"- Bootstrap ({b.replicates} replicates of the fit on its own residuals resampled in "
        f"blocks of {b.block} samples"
        + (f", {b.failed} failed" if b.failed else "")
        + "), σ of the gains (N·m/A) and its ratio to the reported σ: "
        + ", ".join(
            f"{nm} {_g(float(s), 2)} ({float(r):.2f})"
            for nm, s, r in zip(names, b.gain_std, ratio, strict=True)
        )
        + ".",
    ]
