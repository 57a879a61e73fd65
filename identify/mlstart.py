"""The linear least squares that starts the maximum-likelihood gains (:mod:`.ml`).

``V K g − W χ − W_uL χ_uL = W_kL χ_kL`` in torque units, rows of joint j weighted by 1/σ_j of a
first unweighted pass. With noisy currents it is attenuated (errors in variables); it starts the
likelihood search and is the plain LS of the errors-in-variables test (:mod:`.eiv`). Apart from
:mod:`.ml` so that the test's score sums, which the likelihood's covariance pass accumulates,
need not import the likelihood.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivegain.identify.estimate import r_factor
from drivegain.identify.mlmodel import RunArrays, chunks, ls_rows

__all__ = ["LinearStart", "least_squares"]


@dataclass(frozen=True)
class LinearStart:
    """The least squares with V as regressor (:func:`least_squares`).

    Attributes
    ----------
    theta
        (χ, g, χ_uL) of the row-weighted least squares.
    weights
        Row weight of each joint, 1/σ_j from a first unweighted pass, 1/(N·m), (n,).
    hessian
        Its normal matrix Σ_k Σ_j w_j² m_kjᵀ m_kj, (P, P) (m_kj the rows of
        :func:`~.mlmodel.ls_rows`).
    """

    theta: np.ndarray
    weights: np.ndarray
    hessian: np.ndarray


def least_squares(runs: Sequence[RunArrays], kt: np.ndarray) -> LinearStart:
    """θ of the least squares ``V K g − W χ − W_uL χ_uL = W_kL χ_kL`` (torque units).

    One pass over the samples in row blocks: each joint's rows ``[m_j | τ_kL,j]`` are reduced
    to their R factor, from which both passes' solutions, the per-joint residual norms and the
    normal matrix follow (``RᵀR = [m | τ]ᵀ[m | τ]``); no (samples × joints × unknowns) matrix
    is ever held whole.
    """
    n = runs[0].v.shape[1]
    p = runs[0].base_idx.size + n + runs[0].nu
    factors = np.zeros((n, p + 1, p + 1))
    samples = 0
    for run in runs:
        for sl in chunks(run.samples):
            sub = run.rows(sl)
            aug = np.concatenate([ls_rows(sub, kt), sub.tau_known[:, :, None]], axis=2)
            for j in range(n):
                factors[j] = r_factor(np.vstack([factors[j], aug[:, j, :]]))
            samples += sub.samples
    return _from_factors(factors, samples)


def _from_factors(factors: np.ndarray, samples: int) -> LinearStart:
    """Both passes of the weighted least squares from each joint's R factor of ``[m_j | τ_j]``
    ((n, P + 1, P + 1)) over ``samples`` samples."""
    n, p = factors.shape[0], factors.shape[1] - 1

    def solve(weights: np.ndarray) -> np.ndarray:
        r = r_factor((factors * weights[:, None, None]).reshape(-1, p + 1))
        theta, *_ = np.linalg.lstsq(r[:p, :p], r[:p, p], rcond=None)
        return np.asarray(theta)

    w = np.ones(n)
    theta = solve(w)
    x_aug = np.append(theta, -1.0)
    sigma = np.sqrt(np.array([np.sum((f @ x_aug) ** 2) for f in factors]) / samples)
    top = float(sigma.max())
    if top > 0.0:
        w = 1.0 / np.maximum(sigma, 1e-9 * top)
        theta = solve(w)
    gram = np.einsum("jkp,jkq->jpq", factors[:, :, :p], factors[:, :, :p])
    return LinearStart(theta=theta, weights=w, hessian=np.einsum("j,jpq->pq", w**2, gram))
