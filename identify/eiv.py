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
from typing import TYPE_CHECKING

import numpy as np

from drivegain.config.payload import Payload
from drivegain.identify.design import Design
from drivegain.identify.hac import LongRunSum
from drivegain.identify.mlmodel import (
    RunArrays,
    Whitening,
    chunks,
    ls_rows,
    run_pair,
    scores,
    whitened_block,
)
from drivegain.identify.mlstart import LinearStart, least_squares

if TYPE_CHECKING:  # ml sums the test's scores in its covariance pass: it imports this module
    from drivegain.identify.ml import MLFit

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


class InfluenceSums:
    """The per-sample influences of both estimators of the test, summed in one pass.

    The least squares' influence on the gains is ``ψ_ls,k H_ls⁻¹[:, g]`` (its scores
    ψ_ls,k = −Σ_j w_j² e_kj m_kj: rows m_kj, equation errors e_kj, row weights w_j); the
    likelihood's is ``ψ_ml,k H⁻¹[:, g]`` (ψ_ml,k = J̃_kᵀ ẽ_k), whose H is the bread its
    covariance pass is still summing. So the pass sums [LS influence (n), ψ_ml (P)] in one
    Newey-West long-run sum S (:class:`~.hac.LongRunSum`), and the covariance of any
    combination is a quadratic form in S once H is known: the sums ride along the likelihood's
    covariance pass, which has J̃ and ẽ at hand (:func:`~drivegain.identify.ml.ml_fit`).

    Parameters
    ----------
    ls
        The least squares of the test.
    kt
        Coupling factor of the current matrix, (n, n).
    lag
        Newey-West lag, samples.
    nb
        Base parameters (the gains follow them in θ).
    """

    def __init__(self, ls: LinearStart, kt: np.ndarray, lag: int, nb: int):
        self._ls = ls
        self._kt = np.asarray(kt, float)
        n = self._kt.shape[0]
        self._proj = np.linalg.pinv(ls.hessian, hermitian=True)[:, nb : nb + n]
        self._sum = LongRunSum(n + ls.theta.size, lag)

    def add(self, sub: RunArrays, jw: np.ndarray, ew: np.ndarray) -> None:
        """The next rows ``sub`` of the current run, with the likelihood's whitened Jacobian
        ``jw`` (rows, n, P) and residuals ``ew`` (rows, n) there
        (:func:`~.mlmodel.whitened_block`)."""
        m = ls_rows(sub, self._kt)
        e = m @ self._ls.theta - sub.tau_known
        infl_ls = -np.matmul((e * self._ls.weights**2)[:, None, :], m)[:, 0, :] @ self._proj
        self._sum.add(np.hstack([infl_ls, scores(jw, ew)]))

    def end_run(self) -> None:
        """Close the current run."""
        self._sum.end_run()

    def merge(self, other: InfluenceSums) -> None:
        """Add the closed runs of ``other`` (same least squares and lag)."""
        self._sum.merge(other._sum)

    def meat(self) -> np.ndarray:
        """S of [LS influence on the gains, ψ_ml], (n + P, n + P)."""
        return self._sum.meat()


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
        :func:`~.mlmodel.run_pair` of a and b when the caller has it already.
    ls
        :func:`~drivegain.identify.mlstart.least_squares` of those runs when already computed
        (:attr:`~drivegain.identify.ml.MLFit.linear`).

    Returns
    -------
    EIVTest
        Statistic, p-value and the LS gains beside the ML ones.
    """
    from scipy.stats import chi2

    nb, n = fit.nb, a.n
    if fit.influence is not None and fit.linear is not None and (ls is None or ls is fit.linear):
        # summed in the fit's covariance pass (ml_fit(influence=True))
        ls, meat = fit.linear, fit.influence
    else:
        if runs is None:
            runs = run_pair(a, b, payload)
        kt = np.asarray(a.kt, float)
        kt_inv = np.linalg.inv(kt)
        if ls is None:
            ls = least_squares(runs, kt)
        theta_ml = fit.theta
        whiten = Whitening(fit.noise, fit.kappa)
        sums = InfluenceSums(ls, kt, fit.lag, nb)
        for run in runs:
            for sl in chunks(run.samples):
                sub = run.rows(sl)
                sums.add(sub, *whitened_block(theta_ml, sub, kt_inv, whiten))
            sums.end_run()
        meat = sums.meat()
    gains = slice(nb, nb + n)
    # Only the gains' rows of each sample's first-order influence H⁻¹ψ_k enter the test, and
    # the long-run sum is bilinear: the difference's covariance is a quadratic form in S.
    proj_ml = np.linalg.pinv(fit.hessian, hermitian=True)[:, gains]
    q = np.vstack([np.eye(n), -proj_ml])  # [LS influence, ψ_ml] q = LS's − ML's influence
    cov_d = q.T @ meat @ q
    cov_ls = meat[:n, :n]
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
