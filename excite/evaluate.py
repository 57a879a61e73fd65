"""Metrics of an excitation trajectory (stored in ``TRAJ.json``'s ``metrics``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from drivegain.config.payload import Payload
from drivegain.config.robot import Robot
from drivegain.dynamics.model import build_model
from drivegain.dynamics.params import inertial_slice
from drivegain.dynamics.regressor import standard_regressor
from drivegain.excite.criteria import (
    DesignModel,
    design_currents,
    design_model,
    observation_matrix,
    scaled_cond,
    singular_gap,
    wtls_design,
    wtls_matrix,
)
from drivegain.formats.fourier import FourierTrajectory

#: Samples over one period for the stored metrics.
METRIC_SAMPLES = 1000

COND_SCALING = (
    "base observation matrix over one period ({samples} uniform samples), rows stacked "
    "joint-major and unweighted, columns scaled to unit norm; identically zero base columns "
    "left out"
)


def period_regressor(
    design: DesignModel, fourier: FourierTrajectory, samples: int = METRIC_SAMPLES
) -> np.ndarray:
    """Standard regressor (samples, n, p_std) on a uniform grid over one period."""
    t = np.arange(samples) * fourier.period_s / samples
    q, qd, qdd, _ = fourier.evaluate(t)
    return standard_regressor(design.model, q, qd, qdd)


def evaluate_metrics(
    robot: Robot,
    fourier: FourierTrajectory,
    *,
    payload: Payload | None = None,
    chi_nominal: np.ndarray | None = None,
    design: DesignModel | None = None,
    samples: int = METRIC_SAMPLES,
) -> dict[str, Any]:
    """Condition numbers and related figures of a trajectory.

    Returns
    -------
    dict
        ``cond`` (unit-norm columns, see ``cond_scaling``), ``cond_unscaled`` (SI units),
        ``logdet`` (``log det(AᵀA) / p`` unscaled, larger is better), ``samples``; with a payload
        and nominal parameters also ``wtls_cond`` (s_1/s_(p-1) of the design-time W_tot with
        unit-norm columns) and ``payload_torque_rms`` (N·m per joint: how much each joint
        feels the payload, joint 1 included).
    """
    design = design if design is not None else design_model(build_model(robot))
    w = period_regressor(design, fourier, samples)
    a = observation_matrix(design, w)
    s = np.linalg.svd(a, compute_uv=False)
    out: dict[str, Any] = {
        "cond": scaled_cond(a),
        "cond_scaling": COND_SCALING.format(samples=samples),
        "cond_unscaled": float(s[0] / s[-1]),
        "logdet": float(2.0 * np.sum(np.log(s)) / s.shape[0]),
        "samples": samples,
        "base_columns": design.n_kept,
    }
    if payload is not None and chi_nominal is not None:
        wt = wtls_design(robot, chi_nominal, payload)
        v_a, v_b = design_currents(design, wt, w)
        _, wtls_cond, _ = singular_gap(wtls_matrix(design, wt, w, v_a, w, v_b))
        out["wtls_cond"] = wtls_cond
        cols = inertial_slice(payload.link - 1)
        tau_l = w[:, :, cols] @ np.nan_to_num(payload.values, nan=0.0)
        out["payload_torque_rms"] = [float(x) for x in np.sqrt(np.mean(tau_l**2, axis=0))]
    return out
