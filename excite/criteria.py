"""Excitation criteria on the observation matrices, with their gradients.

All criteria are functions of the standard regressor ``W_std`` (N, n, p_std) sampled along the
trajectory; each returns its value and ``dF/dW_std`` so that the optimiser can chain it with the
derivatives of the regressor with respect to the joint states (see :mod:`.optimise`).

Column scaling (stated because a condition number depends on it):

- ``cond``: the base-parameter observation matrix (rows stacked joint-major, rows unweighted)
  with every column scaled to unit Euclidean norm over the sampled period. This makes the
  number independent of the parameters' units, and it is within a factor sqrt(p) of the
  smallest condition number over all column scalings (van der Sluis).
- ``logdet`` (D-optimality): ``-log det(WᵀW) / p_b`` on the unscaled matrix; a fixed column
  scaling only adds a constant, so it needs none.
- ``wtls``: the stacked unloaded + loaded IDIM-WTLS matrix of Gautier & Briot (2012, eq. 15),
  ``W_tot = [-W, V_a, 0, 0; -W, V_b, -W_uL, -W_kL·χ_kL]``, columns scaled to unit norm (this also
  removes the V-column weight α). Noise-free, W_tot has a one-dimensional null space (the
  solution); the criterion is ``s_1 / s_(p-1)``, the condition number on the complement of that
  null space, i.e. it widens the gap between the two smallest singular values.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from drivegain.config.payload import Payload
from drivegain.config.robot import Robot
from drivegain.dynamics.base import BaseParameters, base_parameters
from drivegain.dynamics.model import RobotModel
from drivegain.dynamics.params import inertial_slice, standard_names, with_payload
from drivegain.dynamics.regressor import stack_joint_major
from drivegain.dynamics.transmission import current_matrix, currents_for_torque

#: Smallest singular value used by the criteria, relative to the largest.
SINGULAR_FLOOR = 1e-12


class Criterion(StrEnum):
    """Criterion on the base-parameter observation matrix."""

    COND = "cond"
    LOGDET = "logdet"


@dataclass(frozen=True)
class DesignModel:
    """What the criteria need to know about the robot model.

    Attributes
    ----------
    model
        The robot model.
    base
        Its base parameters.
    sign_columns
        Standard indices of the Coulomb columns (sign of a velocity): their derivative with
        respect to the state is zero almost everywhere.
    """

    model: RobotModel
    base: BaseParameters
    sign_columns: np.ndarray

    @property
    def robot(self) -> Robot:
        return self.model.robot

    @property
    def kept(self) -> np.ndarray:
        """Standard-parameter indices of the base columns the criteria use."""
        return np.asarray(self.base.base_index)

    @property
    def kept_names(self) -> list[str]:
        """Their base names."""
        return list(self.base.names)

    @property
    def n_kept(self) -> int:
        return int(self.kept.shape[0])


def design_model(
    model: RobotModel, base: BaseParameters | None = None, *, seed: int = 0
) -> DesignModel:
    """Prepare the criteria for ``model``: its base parameters (which already leave out columns
    without effect) and the Coulomb columns."""
    base = base if base is not None else base_parameters(model, seed=seed)
    names = standard_names(model.robot)
    sign = np.array([i for i, nm in enumerate(names) if nm.startswith(("Fc", "fcm"))], dtype=int)
    return DesignModel(model=model, base=base, sign_columns=sign)


def observation_matrix(design: DesignModel, w_std: np.ndarray) -> np.ndarray:
    """Base observation matrix (n·N, p_b), rows stacked joint-major, unscaled."""
    return stack_joint_major(np.asarray(w_std)[:, :, design.kept])


def unit_columns(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``a`` with unit-norm columns, and the norms. Zero columns stay zero."""
    norms = np.linalg.norm(a, axis=0)
    safe = np.where(norms > 0.0, norms, 1.0)
    return a / safe, safe


def scaled_cond(a: np.ndarray) -> float:
    """Condition number of ``a`` with unit-norm columns (the ``cond`` criterion, not logged)."""
    s = np.linalg.svd(unit_columns(a)[0], compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def _gram_pairs(
    m: np.ndarray, which: tuple[int, ...]
) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Singular values (descending) of a tall ``m`` and the singular pairs (u, v) at ``which``.

    Through the eigen-decomposition of the small Gram matrix mᵀm: far cheaper than an SVD of the
    tall matrix and accurate while the condition number stays below about 1e6 (squaring it
    then loses nothing that matters); beyond, an SVD of ``m`` itself. Singular values are
    floored at :data:`SINGULAR_FLOOR` times the largest, so that a degenerate point (a joint
    at rest, a zero column) gives a large finite criterion rather than infinity.
    """
    w, vecs = np.linalg.eigh(m.T @ m)
    w, vecs = w[::-1], vecs[:, ::-1]
    if w[-1] > 1e-12 * w[0]:
        s = np.sqrt(w)
    else:
        _, s, vt = np.linalg.svd(m, full_matrices=False)
        vecs = vt.T
    s = np.maximum(s, SINGULAR_FLOOR * s[0])
    pairs = []
    for i in which:
        v = vecs[:, i]
        pairs.append((m @ v / s[i], v))
    return s, pairs


def _unscale_gradient(m: np.ndarray, h: np.ndarray, norms: np.ndarray) -> np.ndarray:
    """Gradient with respect to A from the one with respect to M = A·diag(1/||a_k||)."""
    return (h - m * np.sum(m * h, axis=0)) / norms


def _unstack(x: np.ndarray, n: int) -> np.ndarray:
    """Inverse of joint-major stacking on rows: (n·N, p) -> (N, n, p)."""
    return x.reshape(n, -1, x.shape[1]).transpose(1, 0, 2)


def base_criterion(
    design: DesignModel, w_std: np.ndarray, criterion: Criterion | str
) -> tuple[float, np.ndarray]:
    """Value and gradient of a base-matrix criterion (to minimise).

    ``cond``: log of the condition number with unit-norm columns. ``logdet``:
    ``-log det(AᵀA) / p_b`` with A unscaled.

    Returns
    -------
    tuple
        ``(value, dvalue/dW_std)`` with the gradient shaped like ``w_std``.
    """
    crit = Criterion(criterion)
    n = design.robot.n
    a = observation_matrix(design, w_std)
    grad = np.zeros_like(w_std)
    if crit is Criterion.COND:
        m, norms = unit_columns(a)
        s, ((u1, v1), (up, vp)) = _gram_pairs(m, (0, a.shape[1] - 1))
        value = float(np.log(s[0] / s[-1]))
        h = np.outer(u1, v1) / s[0] - np.outer(up, vp) / s[-1]
        ga = _unscale_gradient(m, h, norms)
    else:
        w, vecs = np.linalg.eigh(a.T @ a)
        w = np.maximum(w, SINGULAR_FLOOR**2 * w[-1])
        p = w.shape[0]
        value = float(-np.sum(np.log(w)) / p)
        ga = -2.0 / p * (a @ (vecs / w)) @ vecs.T
    grad[:, :, design.kept] = _unstack(ga, n)
    return value, grad


@dataclass(frozen=True)
class WtlsDesign:
    """Nominal values behind the design-time WTLS matrix.

    Attributes
    ----------
    chi, chi_loaded
        Nominal standard parameters without and with the payload.
    gains
        Gains (N·m/A) turning nominal torques into current references (the a priori gains).
    unknown, known
        Standard indices of the payload parameters WTLS identifies and of those it knows.
    known_values
        Values of the known payload parameters.
    """

    chi: np.ndarray
    chi_loaded: np.ndarray
    gains: np.ndarray
    unknown: np.ndarray
    known: np.ndarray
    known_values: np.ndarray


def wtls_design(
    robot: Robot, chi: np.ndarray, payload: Payload, gains: np.ndarray | None = None
) -> WtlsDesign:
    """The WTLS criterion's nominal values for a payload (gains default to the a priori ones)."""
    cols = np.arange(inertial_slice(payload.link - 1).start, inertial_slice(payload.link - 1).stop)
    mask = payload.known_mask()
    return WtlsDesign(
        chi=np.asarray(chi, float),
        chi_loaded=with_payload(robot, chi, payload),
        gains=robot.apriori_gains if gains is None else np.asarray(gains, float),
        unknown=cols[~mask],
        known=cols[mask],
        known_values=payload.values[mask],
    )


def wtls_matrix(
    design: DesignModel,
    wtls: WtlsDesign,
    w_a: np.ndarray,
    v_a: np.ndarray,
    w_b: np.ndarray,
    v_b: np.ndarray,
) -> np.ndarray:
    """The unscaled, unweighted WTLS matrix (eq. 15) of an unloaded and a loaded run.

    Parameters
    ----------
    design, wtls
        Model and payload description.
    w_a, w_b
        Standard regressors (N, n, p_std) of the unloaded and loaded runs.
    v_a, v_b
        Current references (N, n), A.

    Returns
    -------
    numpy.ndarray
        Columns ``[base (p_b) | gains (n) | unknown payload | known payload·χ_kL]``; the null
        vector is ``[χ_base, g, χ_uL, 1]``.
    """
    robot = design.robot
    n, nb, nu = robot.n, design.n_kept, wtls.unknown.shape[0]
    w_a, w_b = np.asarray(w_a), np.asarray(w_b)
    rows_a, rows_b = n * w_a.shape[0], n * w_b.shape[0]
    out = np.zeros((rows_a + rows_b, nb + n + nu + 1))
    out[:rows_a, :nb] = -observation_matrix(design, w_a)
    out[rows_a:, :nb] = -observation_matrix(design, w_b)
    out[:rows_a, nb : nb + n] = stack_joint_major(current_matrix(robot, v_a))
    out[rows_a:, nb : nb + n] = stack_joint_major(current_matrix(robot, v_b))
    out[rows_a:, nb + n : nb + n + nu] = -stack_joint_major(w_b[:, :, wtls.unknown])
    out[rows_a:, -1] = -stack_joint_major(w_b[:, :, wtls.known] @ wtls.known_values)
    return out


def design_currents(
    design: DesignModel, wtls: WtlsDesign, w_std: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Nominal current references (N, n) of the unloaded and loaded runs along ``w_std``."""
    robot = design.robot
    v_a = currents_for_torque(robot, w_std @ wtls.chi, wtls.gains)
    v_b = currents_for_torque(robot, w_std @ wtls.chi_loaded, wtls.gains)
    return v_a, v_b


def singular_gap(a: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Singular values of ``a`` with unit-norm columns, ``s_1/s_(p-1)`` and ``s_(p-1)/s_p``."""
    s = np.linalg.svd(unit_columns(a)[0], compute_uv=False)
    return s, float(s[0] / s[-2]), float(s[-2] / s[-1]) if s[-1] > 0 else float("inf")


def wtls_criterion(
    design: DesignModel, wtls: WtlsDesign, w_std: np.ndarray
) -> tuple[float, np.ndarray]:
    """Value and gradient of ``log(s_1 / s_(p-1))`` of the design-time W_tot (to minimise).

    The same trajectory is used for the unloaded and the loaded run (as the demo does), and
    the current references are the nominal torques through the a priori gains.
    """
    robot = design.robot
    n, nb, nu = robot.n, design.n_kept, wtls.unknown.shape[0]
    w_std = np.asarray(w_std)
    v_a, v_b = design_currents(design, wtls, w_std)
    a = wtls_matrix(design, wtls, w_std, v_a, w_std, v_b)
    m, norms = unit_columns(a)
    s, ((u1, v1), (uq, vq)) = _gram_pairs(m, (0, a.shape[1] - 2))
    value = float(np.log(s[0] / s[-2]))
    h = np.outer(u1, v1) / s[0] - np.outer(uq, vq) / s[-2]
    ga = _unscale_gradient(m, h, norms)
    rows = ga.shape[0] // 2
    ha, hb = _unstack(ga[:rows], n), _unstack(ga[rows:], n)
    grad = np.zeros_like(w_std)
    grad[:, :, design.kept] -= ha[:, :, :nb] + hb[:, :, :nb]
    grad[:, :, wtls.unknown] -= hb[:, :, nb + n : nb + n + nu]
    grad[:, :, wtls.known] -= hb[:, :, -1:] * wtls.known_values
    # V = kt ∘ v (column j scaled by v_j), v = A⁻¹ τ with A = kt·diag(g), τ = W_std χ.
    k = robot.transmission()
    kt = k.T / np.diag(k)[None, :]
    a_mat = kt * wtls.gains[None, :]
    a_inv = np.linalg.inv(a_mat)
    for hv, chi in ((ha, wtls.chi), (hb, wtls.chi_loaded)):
        dv = np.einsum("nij,ij->nj", hv[:, :, nb : nb + n], kt)
        dtau = dv @ a_inv
        grad += dtau[:, :, None] * chi[None, None, :]
    return value, grad
