"""IDIM-WTLS at one α: the weighted total-least-squares solve and its covariance.

The total matrix ``[−W_a, αV_a, 0, 0; −W_b, αV_b, −W_uL, −W_kL·χ_kL]`` (Gautier & Briot 2012,
eq. 19), rows weighted by 1/σ_j, is solved by the smallest right singular vector scaled so that
δ = 1 (:func:`wtls_fit`); σ_j are re-estimated from the WTLS residuals until they settle
(σ_j from OLS with wrong a priori gains spoils the coupled joints 5-6, docs/model.md).

The gains' standard deviations come from a first-order (sandwich) covariance of the TLS solution
whose scores are summed over clusters of possibly correlated samples, including the same phase
of a periodic excitation in every period (:func:`wtls_covariance`): encoder quantisation
repeats exactly from one period to the next.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivegain.config.payload import Payload
from drivegain.identify.design import Design, tls_transform
from drivegain.identify.estimate import (
    TLSResult,
    cluster_sums,
    r_factor,
    tls_covariance,
    tls_from_factor,
    tls_scores,
)
from drivegain.identify.weighting import (
    EXACT_TOL,
    SIGMA_MAX_ITER,
    SIGMA_TOL,
    drive_noise_weights,
    floor_sigma,
)


@dataclass(frozen=True)
class WTLSFit:
    """One IDIM-WTLS solution at a given α, after the σ_j iteration.

    Attributes
    ----------
    alpha
        Weight of the V columns.
    column_weights
        Weight of each drive's V column: α times the noise balance of
        :func:`~drivegain.identify.weighting.drive_noise_weights` (``tls.x`` holds g / column
        weight).
    sigma
        Per-joint σ̂_j from the WTLS residuals, N·m.
    tls
        The TLS solution of the weighted matrix.
    chi, gains, payload_unknown
        The solution unscaled: base parameters, gains (N·m/A), unknown payload parameters.
    relative_error
        ‖ρ‖/‖Y‖ of the equation errors weighted by 1/σ_j (the α criterion).
    relative_error_unweighted
        ‖ρ‖/‖Y‖ unweighted, N·m (as in Table 4).
    iterations, converged
        σ iteration count and whether it settled.
    """

    alpha: float
    column_weights: np.ndarray
    sigma: np.ndarray
    tls: TLSResult
    chi: np.ndarray
    gains: np.ndarray
    payload_unknown: np.ndarray
    relative_error: float
    relative_error_unweighted: float
    iterations: int
    converged: bool


def wtls_fit(
    designs: tuple[Design, Design],
    factors: tuple[np.ndarray, np.ndarray],
    payload: Payload,
    alpha: float,
    sigma0: np.ndarray,
    gains0: np.ndarray,
    *,
    iterate: bool = True,
    balance: bool = True,
) -> WTLSFit:
    """IDIM-WTLS at one α, re-estimating σ_j (and the drive weights) from its own residuals.

    Parameters
    ----------
    designs, factors
        Runs a and b and their per-joint R factors.
    payload
        Payload of run b.
    alpha
        Weight of the V columns.
    sigma0, gains0
        Starting σ_j (N·m) and gains (for the drive weights).
    iterate
        Re-estimate σ_j from the WTLS residuals until they settle (else keep ``sigma0``).
    balance
        Weight each drive's V column by its noise
        (:func:`~drivegain.identify.weighting.drive_noise_weights`); False gives the paper's
        single α.

    Returns
    -------
    WTLSFit
        The solution at ``alpha`` after the σ_j iteration.

    Raises
    ------
    IdentificationError
        No finite-scale solution (from :func:`~drivegain.identify.estimate.tls_from_factor`).
    """
    a, b = designs
    known = payload.known_mask()
    chi_known = payload.values[known]
    n, nb = a.n, a.nb
    rows_joint = a.rows + b.rows
    rows_total = rows_joint * n

    def setup(sig: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, list[tuple[int, np.ndarray]]]:
        w = alpha * (drive_noise_weights(a.kt, g, sig) if balance else np.ones(n))
        ts = [tls_transform(d, known, chi_known, w) for d in designs]
        # Per run and joint, R_j·T: only the row weights change until the next setup.
        return w, [(j, f[j] @ t) for f, t in zip(factors, ts, strict=True) for j in range(n)]

    def joint_sq(blocks: list[tuple[int, np.ndarray]], x: np.ndarray) -> np.ndarray:
        out = np.zeros(n)
        for j, blk in blocks:
            out[j] += float(np.sum((blk @ x) ** 2))
        return out

    def solve(
        sig: np.ndarray, blocks: list[tuple[int, np.ndarray]]
    ) -> tuple[TLSResult, np.ndarray]:
        r = r_factor(np.vstack([blk / sig[j] for j, blk in blocks]))
        sol = tls_from_factor(r)
        return sol, joint_sq(blocks, sol.x)

    def y_sq_of(blocks: list[tuple[int, np.ndarray]], x: np.ndarray) -> np.ndarray:
        # Y = V g: the same transform with only the V columns kept.
        y_vec = np.zeros_like(x)
        y_vec[nb : nb + n] = x[nb : nb + n]
        return joint_sq(blocks, y_vec)

    sigma = np.asarray(sigma0, dtype=float).copy()
    col_w, blocks = setup(sigma, np.asarray(gains0, dtype=float))
    tls, res_sq = solve(sigma, blocks)
    k = tls.x.size
    converged = not iterate
    it = 0
    while iterate and it < SIGMA_MAX_ITER:
        if res_sq.sum() <= EXACT_TOL**2 * y_sq_of(blocks, tls.x).sum():
            converged = True  # exact data: σ would be round-off, nothing to re-estimate
            break
        it += 1
        new = floor_sigma(np.sqrt(res_sq / (rows_joint * (1.0 - (k - 1) / rows_total))))
        change = float(np.max(np.abs(new / sigma - 1.0)))
        sigma = new
        col_w, blocks = setup(sigma, col_w * tls.x[nb : nb + n])
        tls, res_sq = solve(sigma, blocks)
        if change < SIGMA_TOL:
            converged = True
            break
    x = tls.x
    gains = col_w * x[nb : nb + n]
    y_sq = y_sq_of(blocks, x)
    rel_w = float(np.sqrt(np.sum(res_sq / sigma**2) / np.sum(y_sq / sigma**2)))
    rel_u = float(np.sqrt(res_sq.sum() / y_sq.sum()))
    return WTLSFit(
        alpha=float(alpha),
        column_weights=col_w,
        sigma=sigma,
        tls=tls,
        chi=x[:nb].copy(),
        gains=gains,
        payload_unknown=x[nb + n : -1].copy(),
        relative_error=rel_w,
        relative_error_unweighted=rel_u,
        iterations=it,
        converged=converged,
    )


def residual_block_length(a_rows: Sequence[np.ndarray], max_lag: int) -> int:
    """Block length for the covariance: twice the lag where residual autocorrelation fades.

    ``a_rows`` are per-(run, joint) weighted equation-error series; their mean autocorrelation
    is followed until it falls below 0.1.
    """
    acf = np.zeros(max_lag + 1)
    count = 0
    for r in a_rows:
        r = r - r.mean()
        denom = float(r @ r)
        if denom <= 0 or r.size <= max_lag + 1:
            continue
        spec = np.fft.rfft(r, 2 * r.size)
        full = np.fft.irfft(spec * np.conj(spec))[: max_lag + 1] / denom
        acf += full
        count += 1
    if count == 0:
        return 1
    acf /= count
    below = np.flatnonzero(acf < 0.1)
    lag = int(below[0]) if below.size else max_lag
    return max(1, 2 * lag)


def cluster_labels(
    t: np.ndarray, block: int, period_s: float | None, rate_hz: float
) -> tuple[np.ndarray, int]:
    """Clusters of samples whose equation errors may be correlated, for the covariance.

    Without a known period: blocks of ``block`` consecutive samples. With a periodic
    excitation, errors that depend only on the pose repeat every period (encoder quantisation,
    unmodelled position-dependent effects): then a cluster is a window of ``block`` samples of
    the phase, gathered over all periods. Returns (labels, number of clusters).
    """
    n = t.size
    if period_s is None or period_s * rate_hz < 4 * block or t[-1] - t[0] < 1.5 * period_s:
        labels = np.arange(n) // block
        return labels, int(labels[-1]) + 1 if n else 0
    bins = max(2, int(period_s * rate_hz // block))
    phase = np.mod(t - t[0], period_s) / period_s
    labels = np.minimum((phase * bins).astype(int), bins - 1)
    return labels, bins


def wtls_covariance(
    designs: tuple[Design, Design], payload: Payload, fit: WTLSFit
) -> tuple[np.ndarray, int, int, list[str]]:
    """Sandwich covariance of the unscaled WTLS unknowns (χ, g, χ_uL) at the fit's α and σ.

    Scores are summed over clusters (all joints of a run together, since a current's noise
    enters two rows on the coupled wrist and filtered errors are correlated in time): windows
    of consecutive samples as long as the residuals' autocorrelation, gathered over the
    periods of a periodic excitation (:func:`cluster_labels`). Returns the covariance, the
    window length, the number of clusters and warnings.
    """
    known = payload.known_mask()
    chi_known = payload.values[known]
    transforms = [tls_transform(d, known, chi_known, fit.column_weights) for d in designs]
    x = fit.tls.x
    k = x.size - 1
    weights = 1.0 / fit.sigma
    residuals = []
    for d, t in zip(designs, transforms, strict=True):
        for j in range(d.n):
            residuals.append(weights[j] * (d.block(j) @ (t @ x)))
    min_rows = min(d.rows for d in designs)
    exact = fit.relative_error_unweighted < EXACT_TOL
    block = 1 if exact else residual_block_length(residuals, max_lag=max(1, min_rows // 20))
    meat = np.zeros((k, k))
    n_clusters = 0
    rows = 0
    for d, t in zip(designs, transforms, strict=True):
        labels, count = cluster_labels(d.run.t, block, d.run.period_s, d.run.rate_hz)
        psi_sum = np.zeros((count, k))
        for j in range(d.n):
            psi = tls_scores(weights[j] * (d.block(j) @ t), x)
            psi_sum += cluster_sums(psi, labels, count)
        meat += psi_sum.T @ psi_sum
        n_clusters += count
        rows += d.rows * d.n
    warnings = []
    if n_clusters < 20 and not exact:
        warnings.append(
            f"only {n_clusters} independent groups of samples for the gains' covariance "
            "(long correlation of the residuals or few samples per period): the standard "
            "deviations are themselves uncertain"
        )
    cov_w = tls_covariance(fit.tls, meat, n_clusters, rows)
    # Unscale: the g components of the weighted unknowns are g / column weight.
    nb, n = designs[0].nb, designs[0].n
    scale = np.ones(k)
    scale[nb : nb + n] = fit.column_weights
    return cov_w * np.outer(scale, scale), block, n_clusters, warnings
