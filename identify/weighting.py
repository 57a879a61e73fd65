"""Weights of the IDIM rows and columns: per-joint σ_j and the drives' column balance.

- Rows of joint j are weighted by 1/σ_j. The first σ_j come from an OLS of each joint's
  equations alone (Gautier 1997, :func:`joint_sigma`); IDIM-WTLS then re-estimates them from
  its own residuals (:func:`drivegain.identify.wtls.wtls_fit`), because σ_j from OLS with wrong
  a priori gains spoils the coupled joints 5-6 (docs/model.md).
- The V columns are weighted by α·c_m, where c_m equalises the current noise of the drives as it
  appears in the weighted rows (:func:`drive_noise_weights`); α itself is searched by
  :func:`drivegain.identify.gains.identify_gains`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from drivegain.identify.design import Design
from drivegain.identify.estimate import group_sigma_from_factor, r_factor

#: σ_j iteration (IDIM-WTLS and the global LS it is compared with): stop when no σ_j changes by
#: more than this fraction, or after this many re-estimates.
SIGMA_TOL = 1e-4
SIGMA_MAX_ITER = 30
#: Relative residual below which data count as exact (noise-free simulation): σ_j would be
#: round-off, so it is not re-estimated.
EXACT_TOL = 1e-10


def joint_sigma(
    designs: Sequence[Design], factors: Sequence[np.ndarray], transforms: Sequence[np.ndarray]
) -> np.ndarray:
    """σ̂_j of an OLS fit of joint j's equations alone, for every joint.

    Parameters
    ----------
    designs
        The runs fitted together.
    factors
        Per run, the R factors of every joint's rows, (n, m, m).
    transforms
        Per run, the column transform of the problem
        (:func:`~drivegain.identify.design.ls_transform`).

    Returns
    -------
    numpy.ndarray
        σ̂_j, N·m, (n,), floored by :func:`floor_sigma`.
    """
    n = designs[0].n
    sigma = np.empty(n)
    for j in range(n):
        rows = sum(d.entries(j) for d in designs)
        r = r_factor(np.vstack([f[j] @ t for f, t in zip(factors, transforms, strict=True)]))
        sigma[j] = group_sigma_from_factor(r, rows).sigma
    return floor_sigma(sigma)


def floor_sigma(sigma: np.ndarray) -> np.ndarray:
    """``sigma`` (N·m) with every value raised to at least 1e-9 of the largest.

    Parameters
    ----------
    sigma
        Per-joint σ̂_j, N·m.

    Returns
    -------
    numpy.ndarray
        The floored σ̂_j, N·m.
    """
    # Exact (noise-free) data give σ ≈ 0: keep the weights finite without changing their use.
    top = float(np.max(sigma)) if sigma.size else 0.0
    floor = max(top * 1e-9, 1e-300)
    return np.maximum(sigma, floor)


def drive_noise_weights(kt: np.ndarray, gains: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Relative weights c_m of the V columns that give every drive's column the same noise.

    The equation error of joint j is current noise through the gains:
    σ_j² = Σ_m kt[j,m]²·g_m²·σ_v,m² (eq. 21), which gives the current noise σ_v,m of each drive
    (non-negative least squares; for a robot without coupling σ_v,j = σ_j/|g_j|). In rows weighted
    by 1/σ_j, column m of V then carries noise of variance q_m = mean_j(kt[j,m]²σ_v,m²/σ_j²);
    scaling it by c_m ∝ 1/√q_m (geometric mean 1, so α keeps the paper's meaning) makes the
    noise of the V block isotropic, as total least squares assumes. With a single α for all
    columns (the paper) the solution is biased by about (noise/signal)²·r, which soon exceeds
    its standard deviation: drives with small gains carry more noise in current units.

    Parameters
    ----------
    kt
        Coupling factor of the current matrix (:func:`~drivegain.identify.design.coupling_factor`),
        (n, n).
    gains
        Current estimate of the drive gains, N·m/A, (n,).
    sigma
        Per-joint σ̂_j of the equation errors, N·m, (n,).

    Returns
    -------
    numpy.ndarray
        c_m, dimensionless, (n,), with geometric mean 1.
    """
    from scipy.optimize import nnls

    m_mat = (kt**2) * (np.asarray(gains, float) ** 2)[None, :]
    var_v, _ = nnls(m_mat, np.asarray(sigma, float) ** 2)
    top = float(var_v.max()) if var_v.size else 0.0
    var_v = np.maximum(var_v, 1e-6 * top if top > 0 else 1.0)
    present = kt != 0.0
    q = np.array(
        [
            np.mean((kt[present[:, c], c] ** 2) * var_v[c] / sigma[present[:, c]] ** 2)
            for c in range(kt.shape[1])
        ]
    )
    c = 1.0 / np.sqrt(q)
    return np.asarray(c / np.exp(np.mean(np.log(c))))
