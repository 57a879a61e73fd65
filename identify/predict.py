"""How computed joint torques match measured ones: R² and relative residual norms.

Every case reports them on its own runs; cross-validation and the physically consistent fit
report them on runs held out of the fit.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivegain.identify.design import Design


def predictions(
    designs: Sequence[Design], gains: np.ndarray, chi: np.ndarray, payloads: Sequence[np.ndarray]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Measured and computed joint torques of every design.

    Parameters
    ----------
    designs
        The runs.
    gains
        Drive gains, N·m/A, (n,).
    chi
        Base parameters (SI units of each parameter), (nb,).
    payloads
        Payload parameters of the loaded designs, in their order, (10,) each.

    Returns
    -------
    list of (numpy.ndarray, numpy.ndarray)
        Per design, (measured V·g, computed W·χ + W_L·χ_L), N·m, (N, n) each.
    """
    out = []
    k = 0
    for d in designs:
        chi_l = None
        if d.loaded:
            chi_l = payloads[k]
            k += 1
        out.append((d.torque(gains), d.model_torque(chi, chi_l)))
    return out


@dataclass(frozen=True)
class PredictionQuality:
    """How computed torques match measured ones, all designs together.

    Attributes
    ----------
    r2, joint_relative
        Per joint: R² (NaN for a joint whose torque is constant) and ‖ρ_j‖/‖Y_j‖, (n,) each.
    residual_norm
        ‖ρ‖, N·m, over every sample and joint.
    relative_error
        ‖ρ‖/‖Y‖.
    """

    r2: np.ndarray
    joint_relative: np.ndarray
    residual_norm: float
    relative_error: float


def prediction_quality(pairs: Sequence[tuple[np.ndarray, np.ndarray]]) -> PredictionQuality:
    """Fit quality of measured against computed torques, all designs together.

    Parameters
    ----------
    pairs
        (measured, computed) torques per design, N·m, as :func:`predictions` returns.

    Returns
    -------
    PredictionQuality
        Per joint and overall.
    """
    y = np.concatenate([p[0] for p in pairs])
    res = y - np.concatenate([p[1] for p in pairs])
    ss_res = np.sum(res**2, axis=0)
    ss_tot = np.sum((y - y.mean(axis=0)) ** 2, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = np.where(ss_tot > 0, 1.0 - ss_res / ss_tot, np.nan)
        rel = np.sqrt(ss_res / np.sum(y**2, axis=0))
    return PredictionQuality(
        r2=r2,
        joint_relative=rel,
        residual_norm=float(np.linalg.norm(res)),
        relative_error=float(np.linalg.norm(res) / np.linalg.norm(y)),
    )
