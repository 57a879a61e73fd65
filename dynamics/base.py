"""Base (identifiable) parameters by QR decomposition of a sampled regressor (Gautier 1991).

The numerical rank comes from a column-pivoted QR of the regressor sampled at random states.
The base set is then chosen in the natural parameter order (the first columns that are
independent of the ones before them), which gives the classic regroupings such as
``ZZ1R = ZZ1 + Ia1 + YY2 + ...``: later, dependent parameters are regrouped into earlier ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from drivegain.dynamics.model import RobotModel
from drivegain.dynamics.params import standard_names
from drivegain.dynamics.regressor import stack_joint_major, standard_regressor
from drivegain.errors import ModelError


@dataclass(frozen=True)
class BaseParameters:
    """The base parameters of a model.

    Attributes
    ----------
    standard_names
        Names of all standard parameters.
    base_index, dependent_index
        Indices (into the standard vector) of the base columns and of the regrouped ones.
    beta
        (n_base, n_dependent): ``chi_base = chi[base_index] + beta @ chi[dependent_index]``, and
        ``W[:, dependent_index] = W[:, base_index] @ beta``.
    names
        Base parameter names (``ZZ1R`` when something is regrouped into ``ZZ1``).
    expressions
        Readable regrouping, e.g. ``ZZ1R = ZZ1 + Ia1 + YY2 + 0.0506*M3``.
    rank_tolerance
        Relative tolerance used for the rank decision.
    """

    standard_names: list[str]
    base_index: np.ndarray
    dependent_index: np.ndarray
    beta: np.ndarray
    names: list[str]
    expressions: list[str]
    rank_tolerance: float

    @property
    def n_base(self) -> int:
        return len(self.base_index)

    def matrix(self) -> np.ndarray:
        """Regrouping matrix B (n_base, n_standard) with ``chi_base = B @ chi``."""
        b = np.zeros((self.n_base, len(self.standard_names)))
        b[np.arange(self.n_base), self.base_index] = 1.0
        b[:, self.dependent_index] = self.beta
        return b

    def regroup(self, chi: np.ndarray) -> np.ndarray:
        """Base parameter values from standard ones."""
        chi = np.asarray(chi, dtype=float)
        return chi[..., self.base_index] + chi[..., self.dependent_index] @ self.beta.T

    def columns(self, w_standard: np.ndarray) -> np.ndarray:
        """Base regressor from a standard one (last axis = parameters)."""
        return w_standard[..., self.base_index]


def random_states(
    model: RobotModel, samples: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random joint states within the position limits (and ±velocity/acceleration limits)."""
    r = model.robot
    lo = np.maximum(r.lower, -np.pi)
    hi = np.minimum(r.upper, np.pi)
    q = rng.uniform(lo, hi, size=(samples, r.n))
    qd = rng.uniform(-1.0, 1.0, size=(samples, r.n)) * r.velocity_limits
    qdd = rng.uniform(-1.0, 1.0, size=(samples, r.n)) * r.acceleration_limits
    return q, qd, qdd


def _fmt_coef(c: float) -> str:
    if abs(c - 1.0) < 1e-9:
        return ""
    return f"{c:.6g}*"


def base_parameters(
    model: RobotModel,
    *,
    samples: int = 300,
    seed: int = 0,
    rank_tolerance: float = 1e-8,
) -> BaseParameters:
    """Compute the base parameters of ``model`` from its regressor at random states.

    Parameters
    ----------
    model
        The robot model (its friction form is the robot file's).
    samples
        Random states to sample; each gives n rows.
    seed
        Seed of the random states (the result does not depend on it beyond round-off).
    rank_tolerance
        A column is dependent when its QR diagonal is below this fraction of the largest.
    """
    rng = np.random.default_rng(seed)
    w = stack_joint_major(standard_regressor(model, *random_states(model, samples, rng)))
    # Scale columns to unit norm so the rank decision does not depend on units.
    norms = np.linalg.norm(w, axis=0)
    # Columns of parameters without effect are exactly zero in theory but round-off in practice
    # (MZ2 of the TX-40 comes out near 1e-14): a relative threshold, not "> 0".
    nonzero = norms > rank_tolerance * norms.max()
    ws = w[:, nonzero] / norms[nonzero]
    col_idx = np.flatnonzero(nonzero)
    _, r_piv, _ = scipy.linalg.qr(ws, mode="economic", pivoting=True)
    d_piv = np.abs(np.diag(r_piv))
    rank = int(np.sum(d_piv > rank_tolerance * d_piv[0]))
    r_nat = scipy.linalg.qr(ws, mode="r")[0]
    d_nat = np.abs(np.diag(r_nat))
    independent = d_nat > rank_tolerance * d_nat.max()
    if int(independent.sum()) != rank:
        raise ModelError(
            f"base parameters: natural-order QR found {int(independent.sum())} independent "
            f"columns, pivoted QR rank {rank}; sample more states"
        )
    base_index = col_idx[independent]
    dependent_index = np.setdiff1d(np.arange(w.shape[1]), base_index)
    wb = w[:, base_index]
    beta, *_ = np.linalg.lstsq(wb, w[:, dependent_index], rcond=None)
    # Regrouping coefficients are products of lengths and ratios: clean round-off.
    beta = np.where(np.abs(beta) < 1e-9, 0.0, beta)
    residual = np.abs(wb @ beta - w[:, dependent_index]).max(initial=0.0)
    if residual > 1e-6 * max(1.0, float(np.abs(w).max())):
        raise ModelError(f"base parameters: regrouping residual {residual:.3g} too large")
    names_std = standard_names(model.robot)
    names, exprs = [], []
    for row, k in enumerate(base_index):
        terms = [
            (beta[row, c], names_std[d]) for c, d in enumerate(dependent_index) if beta[row, c]
        ]
        name = names_std[k] + ("R" if terms else "")
        expr = names_std[k]
        for coef, dep in terms:
            sign = "-" if coef < 0 else "+"
            expr += f" {sign} {_fmt_coef(abs(coef))}{dep}"
        names.append(name)
        exprs.append(f"{name} = {expr}" if terms else name)
    return BaseParameters(
        standard_names=names_std,
        base_index=base_index,
        dependent_index=dependent_index,
        beta=beta,
        names=names,
        expressions=exprs,
        rank_tolerance=rank_tolerance,
    )
