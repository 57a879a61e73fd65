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

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivegain.config.payload import Payload
from drivegain.identify.design import Design
from drivegain.identify.hac import LongRunSum
from drivegain.identify.ml import LinearStart, MLFit, least_squares
from drivegain.identify.mlmodel import (
    RunArrays,
    Whitening,
    chunks,
    ls_rows,
    run_arrays,
    scores,
    whitened_block,
)

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


def eiv_test(
    fit: MLFit,
    a: Design,
    b: Design,
    payload: Payload,
    *,
    runs: Sequence[RunArrays] | None = None,
    ls: LinearStart | None = None,
) -> EIVTest:
    """Durbin-Wu-Hausman comparison of plain LS with the ML gains on the same data.

    Parameters
    ----------
    fit
        The maximum-likelihood fit of runs a and b (:func:`~drivegain.identify.ml.ml_fit`).
    a, b, payload
        The designs and payload it was fitted on.
    runs
        ``[run_arrays(a, payload), run_arrays(b, payload)]`` when the caller has them already.
    ls
        :func:`~drivegain.identify.ml.least_squares` of those runs when already computed.

    Returns
    -------
    EIVTest
        Statistic, p-value and the LS gains beside the ML ones.
    """
    from scipy.stats import chi2

    nb, n = a.nb, a.n
    if runs is None:
        runs = [run_arrays(a, payload), run_arrays(b, payload)]
    kt = np.asarray(a.kt, float)
    kt_inv = np.linalg.inv(kt)
    if ls is None:
        ls = least_squares(runs, kt)
    theta_ml = np.concatenate([fit.chi, fit.gains, fit.payload_unknown])
    whiten = Whitening(fit.noise, fit.kappa)
    gains = slice(nb, nb + n)
    # Only the gains' rows of each sample's first-order influence H⁻¹ψ_k enter the test: the
    # per-sample influences are formed block by block, n columns each, never held whole.
    proj_ls = np.linalg.pinv(ls.hessian, hermitian=True)[:, gains]
    proj_ml = np.linalg.pinv(fit.hessian, hermitian=True)[:, gains]
    w2 = ls.weights**2
    diff_sum, ls_sum = LongRunSum(n, fit.lag), LongRunSum(n, fit.lag)
    for run in runs:
        for sl in chunks(run.samples):
            sub = run.rows(sl)
            m = ls_rows(sub, kt)
            e = m @ ls.theta - sub.tau_known
            infl_ls = -np.matmul((e * w2)[:, None, :], m)[:, 0, :] @ proj_ls
            infl_ml = scores(*whitened_block(theta_ml, sub, kt_inv, whiten)) @ proj_ml
            diff_sum.add(infl_ls - infl_ml)
            ls_sum.add(infl_ls)
        diff_sum.end_run()
        ls_sum.end_run()
    cov_d, cov_ls = diff_sum.meat(), ls_sum.meat()
    d = ls.theta[gains] - fit.gains
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
        ls_gains=ls.theta[gains].copy(),
        ls_std=np.sqrt(np.clip(np.diag(cov_ls), 0.0, None)),
        difference_std=np.sqrt(np.clip(np.diag(cov_d), 0.0, None)),
        lag=fit.lag,
    )
