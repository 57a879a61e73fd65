"""Is plain least squares biased on these data? A Durbin-Wu-Hausman test for errors in variables.

Two estimators of the same gains run on the same samples:

- the least squares ``V K g − W χ − W_uL χ_uL = W_kL χ_kL`` (rows of joint j weighted by
  1/σ_j), which treats the currents V as exact regressors: efficient if they are, attenuated
  towards zero when they are noisy (errors in variables);
- the maximum-likelihood estimate of :mod:`drivegain.identify.ml`, which stays consistent when the
  currents are noisy.

Under "the currents are exact" both converge to the true gains and their difference d is noise;
its covariance is the long-run covariance of the difference of the two estimators' per-sample
influences (Newey-West, the ML fit's lag), which needs neither estimator to be efficient. The
statistic ``dᵀ Cov(d)⁻¹ d`` is then χ²-distributed with n degrees of freedom; a small p-value
says plain LS is biased here and the errors-in-variables treatment matters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivegain.config.payload import Payload
from drivegain.identify.design import Design
from drivegain.identify.hac import long_run_covariance
from drivegain.identify.ml import MLFit, linear_start, ls_rows, ml_influence, run_arrays

#: Significance level below which the report says plain LS is biased on the data.
LEVEL = 0.01


@dataclass(frozen=True)
class EIVTest:
    """Outcome of the errors-in-variables test on the gains.

    Attributes
    ----------
    statistic, dof, p_value
        ``dᵀ Cov(d)⁻¹ d``, its degrees of freedom and the χ² tail probability.
    ls_gains, ls_std
        The least-squares gains (N·m/A) and their HAC standard deviations.
    difference_std
        HAC standard deviation of each gain's difference LS − ML, N·m/A.
    lag
        Newey-West lag used, samples.
    """

    statistic: float
    dof: int
    p_value: float
    ls_gains: np.ndarray
    ls_std: np.ndarray
    difference_std: np.ndarray
    lag: int

    @property
    def biased(self) -> bool:
        """Whether plain LS is biased at the :data:`LEVEL` significance level."""
        return self.p_value < LEVEL


def _ls_influence(a: Design, b: Design, payload: Payload) -> tuple[np.ndarray, list[np.ndarray]]:
    """Weighted LS estimate and, per run, each sample's first-order influence on it (N, P)."""
    runs = [run_arrays(a, payload), run_arrays(b, payload)]
    kt = np.asarray(a.kt, float)
    theta, w = linear_start(runs, kt)
    mats = [ls_rows(r, kt) for r in runs]
    resids = [m @ theta - r.tau_known for m, r in zip(mats, runs, strict=True)]
    p = theta.size
    bread = np.zeros((p, p))
    for m in mats:
        flat = (m * w[None, :, None]).reshape(-1, p)
        bread += flat.T @ flat
    h_inv = np.linalg.pinv(bread, hermitian=True)
    infl = [
        -np.matmul((e * w**2)[:, None, :], m)[:, 0, :] @ h_inv
        for m, e in zip(mats, resids, strict=True)
    ]
    return theta, infl


def eiv_test(fit: MLFit, a: Design, b: Design, payload: Payload) -> EIVTest:
    """Durbin-Wu-Hausman comparison of plain LS with the ML gains on the same data.

    Parameters
    ----------
    fit
        The maximum-likelihood fit of runs a and b (:func:`~drivegain.identify.ml.ml_fit`).
    a, b, payload
        The designs and payload it was fitted on.

    Returns
    -------
    EIVTest
        Statistic, p-value and the LS gains beside the ML ones.
    """
    from scipy.stats import chi2

    nb, n = a.nb, a.n
    theta_ls, infl_ls = _ls_influence(a, b, payload)
    infl_ml = ml_influence(fit, a, b, payload)
    gains = slice(nb, nb + n)
    diff_terms = [(l_ - m_)[:, gains] for l_, m_ in zip(infl_ls, infl_ml, strict=True)]
    cov_d = long_run_covariance(diff_terms, fit.lag)
    cov_ls = long_run_covariance([x[:, gains] for x in infl_ls], fit.lag)
    d = theta_ls[gains] - fit.gains
    # Rank from the eigenvalues: a direction with no variance carries no test.
    evals, evecs = np.linalg.eigh(cov_d)
    keep = evals > 1e-12 * max(float(evals.max()), 1e-300)
    proj = evecs[:, keep].T @ d
    stat = float(np.sum(proj**2 / evals[keep]))
    dof = int(np.count_nonzero(keep))
    p_value = float(chi2.sf(stat, dof)) if dof else 1.0
    return EIVTest(
        statistic=stat,
        dof=dof,
        p_value=p_value,
        ls_gains=theta_ls[gains].copy(),
        ls_std=np.sqrt(np.clip(np.diag(cov_ls), 0.0, None)),
        difference_std=np.sqrt(np.clip(np.diag(cov_d), 0.0, None)),
        lag=fit.lag,
    )
