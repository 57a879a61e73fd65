"""Heteroscedasticity- and autocorrelation-consistent (HAC) covariance of M-estimators.

Equation errors of decimated recordings are correlated in time: the anti-aliasing filter spreads
each raw sample's noise over neighbouring decimated samples, and filtered positions carry slowly
varying errors into the regressor. A covariance that assumes independent samples is then too
small. The IDIM-WLS cases (:mod:`drivegain.identify.cases`) and the errors-in-variables test
(:mod:`drivegain.identify.eiv`) write their estimate as a sum of per-sample scores ψ_k and use
the Newey-West (Bartlett kernel) estimate of the scores' long-run covariance here, with the lag
chosen from the data by the AR(1) plug-in rule of Andrews (1991). The ML gains use
:mod:`drivegain.identify.autocov` instead, which this sandwich leaves 10-20 % short there.

Plain functions on numpy arrays; ``series`` are lists of per-run arrays (samples × components),
because correlation is summed within a run, never across two runs.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from drivegain.errors import UsageError

#: Largest lag as a fraction of the shortest run's samples: beyond it the estimate is too noisy.
MAX_LAG_FRACTION = 0.25
#: A run's samples are gathered by the phase of a periodic excitation only when it spans this
#: many periods at least (fewer: most phases would hold one sample).
MIN_PERIODS = 1.5


def _check_series(series: Sequence[np.ndarray]) -> list[np.ndarray]:
    out = [np.asarray(s, dtype=float) for s in series]
    if not out or any(s.ndim != 2 or s.shape[0] < 2 for s in out):
        raise UsageError("series must be a non-empty list of (samples ≥ 2, components) arrays")
    if len({s.shape[1] for s in out}) != 1:
        raise UsageError("every series must have the same number of components")
    return out


def lag1_autocorrelation(series: Sequence[np.ndarray]) -> float:
    """Pooled lag-1 autocorrelation of every component of every series, dimensionless.

    Parameters
    ----------
    series
        Per run, (samples, components) arrays, e.g. whitened residuals.

    Returns
    -------
    float
        Σ x_k x_(k−1) / Σ x_k² over all components and runs (means removed), in (−1, 1).
    """
    num = 0.0
    den = 0.0
    for s in _check_series(series):
        x = s - s.mean(axis=0)
        num += float(np.sum(x[1:] * x[:-1]))
        den += float(np.sum(x * x))
    if den <= 0.0:
        return 0.0
    return float(np.clip(num / den, -0.97, 0.97))


def bartlett_lag(series: Sequence[np.ndarray]) -> int:
    """Newey-West truncation lag from the data (Andrews 1991, AR(1) plug-in, Bartlett kernel).

    ``L = 1.1447 (a N)^(1/3)`` with ``a = 4ρ² / ((1 − ρ)² (1 + ρ)²)``, ρ the pooled lag-1
    autocorrelation (:func:`lag1_autocorrelation`) and N the samples of the shortest run; capped
    at :data:`MAX_LAG_FRACTION` of N.

    Parameters
    ----------
    series
        Per run, (samples, components) arrays whose autocorrelation decides the lag.

    Returns
    -------
    int
        The lag, samples (0 for uncorrelated series).
    """
    series = _check_series(series)
    rho = lag1_autocorrelation(series)
    n = min(s.shape[0] for s in series)
    a = 4.0 * rho**2 / ((1.0 - rho) ** 2 * (1.0 + rho) ** 2)
    lag = int(np.ceil(1.1447 * (a * n) ** (1.0 / 3.0))) if a > 0 else 0
    return int(min(lag, max(0, int(MAX_LAG_FRACTION * n))))


def long_run_covariance(scores: Sequence[np.ndarray], lag: int) -> np.ndarray:
    """Σ over runs of the Bartlett-weighted sum of score autocovariances (the HAC "meat").

    ``S = Σ_runs [Γ_0 + Σ_(l=1..L) (1 − l/(L+1)) (Γ_l + Γ_lᵀ)]`` with
    ``Γ_l = Σ_k ψ_k ψ_(k−l)ᵀ``. The scores must be evaluated at the estimate (they sum to
    zero there); they are not demeaned. Computed by :class:`LongRunSum` in one pass, at a cost
    that does not grow with the lag.

    Parameters
    ----------
    scores
        Per run, (samples, parameters) per-sample scores.
    lag
        Truncation lag L, samples (≥ 0).

    Returns
    -------
    numpy.ndarray
        (parameters, parameters), positive semi-definite.
    """
    scores = _check_series(scores)
    acc = LongRunSum(scores[0].shape[1], lag)
    for s in scores:
        acc.add(s)
        acc.end_run()
    return acc.meat()


class LongRunSum:
    """:func:`long_run_covariance` accumulated over row blocks, so no run is held whole.

    Feed each run's scores in consecutive row blocks of any size (:meth:`add`), then close the
    run (:meth:`end_run`) before the next one starts; :meth:`meat` gives S.

    Why it is exact and cheap: with ``B_k = Σ_(i=0..L) ψ_(k−i)`` the moving sum of L+1 scores
    (ψ zero outside the run, k running L samples past its end),
    ``Σ_k B_k B_kᵀ = Σ_(|l|≤L) (L+1−|l|) Γ_l = (L+1) S``: the Bartlett weights are the counts
    of pairs inside a window. One outer product per sample whatever the lag, where the sum
    over lags costs L of them; a block needs only the previous block's last L scores.
    """

    def __init__(self, params: int, lag: int):
        if lag < 0:
            raise UsageError(f"lag must be ≥ 0, got {lag}")
        self.lag = int(lag)
        self._sum = np.zeros((params, params))
        self._tail = np.zeros((0, params))  # the current run's last ≤ L scores

    def add(self, block: np.ndarray) -> None:
        """Add the next rows of the current run, (rows, parameters)."""
        x = np.asarray(block, dtype=float)
        if x.ndim != 2 or x.shape[1] != self._sum.shape[0]:
            raise UsageError(f"expected (rows, {self._sum.shape[0]}) scores, got {x.shape}")
        if x.shape[0] == 0:
            return
        if self.lag == 0:
            self._sum += x.T @ x
            return
        ext = np.concatenate([self._tail, x])
        cum = np.zeros((ext.shape[0] + 1, ext.shape[1]))
        np.cumsum(ext, axis=0, out=cum[1:])
        first = self._tail.shape[0]
        # B at ext row t: ext[max(0, t−L) .. t]; rows before the run's first are zero.
        stop = np.arange(first, ext.shape[0]) + 1
        moving = cum[stop] - cum[np.maximum(stop - self.lag - 1, 0)]
        self._sum += moving.T @ moving
        self._tail = ext[-self.lag :].copy()

    def end_run(self) -> None:
        """Close the current run: the windows that reach past its last sample."""
        tail = self._tail
        if tail.shape[0]:
            # B of the L samples after the end: sums of the run's last L, L−1, ..., 1 scores
            # (the whole run when it is shorter).
            suffix = np.cumsum(tail[::-1], axis=0)
            counts = np.minimum(np.arange(1, self.lag + 1), tail.shape[0])
            moving = suffix[counts - 1]
            self._sum += moving.T @ moving
        self._tail = np.zeros((0, self._sum.shape[0]))

    def merge(self, other: LongRunSum) -> None:
        """Add the closed runs of ``other`` (same lag and size, e.g. summed in another
        process) to these."""
        if other.lag != self.lag or other._sum.shape != self._sum.shape:
            raise UsageError(f"cannot merge sums of lag {other.lag} into sums of lag {self.lag}")
        if self._tail.shape[0] or other._tail.shape[0]:
            raise UsageError("close every run (end_run) before merging")
        self._sum += other._sum

    def meat(self) -> np.ndarray:
        """S of every run added so far (call :meth:`end_run` after the last one)."""
        return np.asarray(self._sum / (self.lag + 1.0))


def phase_bins(
    t: np.ndarray, period_s: float | None, rate_hz: float, origin_s: float | None = None
) -> tuple[np.ndarray, int] | None:
    """The phase of each sample of a run of a periodic excitation, in bins one sample wide.

    An error that depends on where the excitation is (a misfit of the model at a pose or a
    reversal, rather than noise) comes back every period, so samples one or more periods apart
    are correlated however far apart they are in time. Summing a run's scores by phase bin
    (:func:`~drivegain.identify.estimate.cluster_sums`) before the long-run covariance counts
    those correlations too.

    Parameters
    ----------
    t
        Sample times of the run, s, increasing (gaps allowed).
    period_s
        Period of the excitation, s, or None when it is not periodic.
    rate_hz
        Sample rate of ``t``, Hz.
    origin_s
        Time of phase 0 (the excitation's start) on the clock of ``t``, s; None: the run's
        first sample. Runs whose phases are to be compared need theirs.

    Returns
    -------
    (labels, bins) or None
        The bin of each sample, 0..bins−1 (the nearest), and the number of bins (one period at
        ``rate_hz``); None without a period or when the run spans less than
        :data:`MIN_PERIODS` periods.
    """
    t = np.asarray(t, dtype=float)
    if rate_hz <= 0.0:
        raise UsageError(f"rate_hz must be > 0, got {rate_hz}")
    if period_s is None or not period_s > 0.0 or t.size < 2:
        return None
    if t[-1] - t[0] < MIN_PERIODS * period_s:
        return None
    bins = max(2, round(period_s * rate_hz))
    # the nearest bin: a sample on a bin's edge must not fall to its neighbour by round-off
    phase = np.mod(t - (t[0] if origin_s is None else origin_s), period_s) / period_s
    return np.rint(phase * bins).astype(np.intp) % bins, bins


def sandwich(bread: np.ndarray, meat: np.ndarray, rows: int, params: int) -> np.ndarray:
    """``H⁻¹ S H⁻¹ · rows / (rows − params)``: the HAC covariance with the small-sample factor.

    Parameters
    ----------
    bread
        H, the Hessian (or its Gauss-Newton approximation) of the objective whose per-sample
        gradients are the scores, (p, p).
    meat
        S from :func:`long_run_covariance`, (p, p).
    rows, params
        Scalar equations used and parameters fitted (the degrees-of-freedom correction).

    Returns
    -------
    numpy.ndarray
        Covariance of the estimate, (p, p), symmetric.
    """
    if rows <= params:
        raise UsageError(f"need more equations ({rows}) than parameters ({params})")
    h_inv = np.linalg.pinv(bread, hermitian=True)
    cov = h_inv @ meat @ h_inv * (rows / (rows - params))
    return np.asarray(0.5 * (cov + cov.T))


def matched_root(target: np.ndarray, source: np.ndarray) -> np.ndarray:
    """T = target^½ source^(−½) (symmetric roots), so that T · source · Tᵀ = target.

    Maps a series whose covariance is ``source`` onto one with the covariance ``target``;
    directions in which ``source`` vanishes (below 1e-12 of its largest eigenvalue) map to
    zero.

    Parameters
    ----------
    target, source
        Symmetric positive semidefinite, (n, n), of one unit.
    """

    def roots(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w, v = np.linalg.eigh(0.5 * (m + m.T))
        w = np.clip(w, 0.0, None)
        keep = w > 1e-12 * max(float(w.max(initial=0.0)), np.finfo(float).tiny)
        inv = np.where(keep, 1.0 / np.sqrt(np.where(keep, w, 1.0)), 0.0)
        return (v * np.sqrt(w)) @ v.T, (v * inv) @ v.T

    return np.asarray(roots(target)[0] @ roots(source)[1])


def gathered(folded: Sequence[np.ndarray | None], together: bool) -> list[np.ndarray] | None:
    """The phase sums :func:`with_repeats` takes: None unless every run has them; with
    ``together`` (runs of one excitation whose phases are measured from its start) added into
    one, since a misfit at one phase is then correlated across the runs too."""
    if not folded or any(f is None for f in folded):
        return None
    sums = [f for f in folded if f is not None]
    if together and all(f.shape == sums[0].shape for f in sums):
        return [np.sum(sums, axis=0)]
    return sums


def with_repeats(
    cov: np.ndarray, bread: np.ndarray, folded: Sequence[np.ndarray], lag: int, rows: int
) -> tuple[np.ndarray, np.ndarray]:
    """``cov`` with each standard deviation raised to that of the scores gathered by phase.

    :class:`~drivegain.identify.autocov.LaggedSums` takes the errors as stationary and
    correlated over a few samples. Where the model misses something the excitation repeats
    (the stick of a drive at each reversal, a pose-dependent effect), the misfit comes back
    every period, and the samples of one phase in different periods are correlated: a run of
    P periods then carries up to P times the variance of its misfit that a short lag counts.
    The Newey-West sandwich of the scores summed by phase (:func:`phase_bins`) counts it
    without assuming what repeats. It is the noisier estimate of the two, so it only raises
    σ, entry by entry (the correlations of ``cov`` are kept).

    Parameters
    ----------
    cov
        Covariance from the errors' autocovariance, (P, P).
    bread
        H, (P, P).
    folded
        Per run, its per-sample scores summed by phase bin, (bins, P); runs of one excitation
        whose phases are comparable (the same origin) may be summed into one.
    lag
        The errors' longest lag, samples (one bin is one sample).
    rows
        Scalar equations of the fit (the sandwich's small-sample factor).

    Returns
    -------
    (numpy.ndarray, numpy.ndarray)
        The covariance, (P, P), and the factor (≥ 1) of each standard deviation, (P,).
    """
    by_phase = sandwich(bread, long_run_covariance(folded, lag), rows, bread.shape[0])
    var = np.diag(cov)
    ratio = np.divide(np.diag(by_phase), var, out=np.ones_like(var), where=var > 0.0)
    scale = np.sqrt(np.maximum(ratio, 1.0))
    return cov * np.outer(scale, scale), scale
