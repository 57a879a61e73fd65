"""Covariance of a fitted estimate from its errors' autocovariance, corrected for the fit.

Why not the Newey-West estimate of :mod:`drivegain.identify.hac` alone: the decimated equation
errors of a recording are correlated over a few samples (the anti-aliasing filter passes
0.8 of the new band, so white noise comes out with a lag-1 autocorrelation near +0.2 and an
alternating tail: its long-run variance is 1.16-1.25 times its variance). The gains are
carried by the slow content of the regressor, where that excess lives, and the fit removes
exactly that slow content from the residuals: the residuals' autocorrelations come out too
small, and a Bartlett-weighted sum of the scores' autocovariances shrinks them further. In the
validation study's torque-noise scenarios the HAC σ was 10-20 % too small on every estimator.

Here the whitened errors ``e`` of every run are taken as stationary, with one autocovariance
sequence γ_0..γ_L shared by all components (whitening makes the lag-0 covariance the identity,
and one filter acts on every drive's errors): ``Cov(e) = Ω = Σ_m γ_m V_m ⊗ I_n``, V_0 = I,
V_m = S_m + S_mᵀ (S_m shifts by m samples within a run). The residuals are ``ê = M e``,
``M = I − J H⁻¹ Jᵀ`` (J the whitened Jacobian, H = JᵀJ), so the residual lag sums
``q_l = Σ_k ê_(k+l)·ê_k`` have ``E q_l = Σ_m γ_m tr(U_l M V_m M)`` (U_0 = I, U_l = V_l / 2):
a small linear system gives γ without the fit's bias. The covariance is then
``H⁻¹ (Jᵀ Ω̂ J) H⁻¹``, and ``Jᵀ V_m J`` are the lagged Gram matrices the system needs anyway.
Everything is accumulated over row blocks (:class:`LaggedSums`), so no run is held whole.

Terms that pair a shift with another (``Jᵀ V_l V_m J``) are taken as ``Jᵀ (V_(l+m) + V_|l−m|) J``,
which leaves out products of the first and last L samples of a run: an error of order L/N on
the correction, itself of order P/N.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivegain.errors import UsageError

#: Relative size of a negative eigenvalue of the (scaled) meat taken as round-off.
PSD_TOL = 1e-10
#: Samples per sub-block of :meth:`LaggedSums.add`: ~3 000 rows of ~75 columns, whose lagged
#: products stay in cache (about 10 % faster than sub-blocks of 2048 samples).
SUB_BLOCK = 512


@dataclass(frozen=True)
class ErrorAutocovariance:
    """The errors' autocovariance the covariance was computed with.

    Attributes
    ----------
    gamma
        γ_0..γ_L of the whitened errors (dimensionless; γ_0 ≈ 1 for white errors whose
        variance the whitening knew), corrected for the fit.
    long_run
        ``(γ_0 + 2 Σ γ_m) / γ_0``: how much the errors' slow content exceeds that of white
        errors of the same variance (dimensionless).
    tapered
        The raw sequence gave a meat ``Jᵀ Ω̂ J`` that is not positive semi-definite, so it was
        Bartlett weighted (``γ_m (1 − m/(L+1))``); if that still failed, the lags were dropped.
    """

    gamma: np.ndarray
    long_run: float
    tapered: bool


class LaggedSums:
    """One pass over the whitened Jacobian and residuals of every run, in row blocks.

    Feed each run's consecutive row blocks with :meth:`add` and close it with :meth:`end_run`
    before the next run; :meth:`covariance` then gives the estimate's covariance.

    Runs may also be fed to separate instances (one per process) and joined with
    :meth:`merge`.

    The lagged Grams ``D_d = Σ_k (J_kᵀ J_(k+d) + J_(k+d)ᵀ J_k)`` take almost all of the time
    (L + 1 products of (rows·n, P) blocks). Each is summed as
    ``Σ_k (J_k + J_(k+d))ᵀ (J_k + J_(k+d))`` less the two lag-0 sums it contains, which are
    the run's H less the Grams of its first or last d samples: a product of a block with
    itself costs about half of a general one. Blocks are taken :data:`SUB_BLOCK` samples at a
    time, which stay in cache across the lags.

    Parameters
    ----------
    h_inv
        H⁻¹ for the fit's projection: the inverse (or pseudo-inverse) of ``Σ J_kᵀ J_k`` over
        every run, or of a close approximation such as the last Gauss-Newton step's, (P, P).
        It enters only the correction for the fit (a term of order P/N), so a relative error ε
        in it moves the covariance by about ε·P/N. The sandwich's bread is always the exact
        ``Σ J_kᵀ J_k`` accumulated here (:attr:`bread`).
    lag
        L, the longest lag of the errors' autocovariance, samples (≥ 0).
    """

    def __init__(self, h_inv: np.ndarray, lag: int):
        h_inv = np.asarray(h_inv, dtype=float)
        if h_inv.ndim != 2 or h_inv.shape[0] != h_inv.shape[1]:
            raise UsageError(f"h_inv must be square, got shape {h_inv.shape}")
        if lag < 0:
            raise UsageError(f"lag must be ≥ 0, got {lag}")
        self.lag = int(lag)
        self._h_inv = h_inv
        p = h_inv.shape[0]
        self._gram = np.zeros((self.lag + 1, p, p))  # H, then D_1..D_L (closed runs)
        # tr(H⁻¹ G_d), G_d = Σ_k J_kᵀ J_(k+d), for L < d ≤ 2L (those up to L come from D_d)
        self._trace = np.zeros(2 * self.lag + 1)
        self._q = np.zeros(self.lag + 1)  # Σ_k ê_(k+l)·ê_k
        self._count = np.zeros(self.lag + 1)  # Σ_runs n (N − l)
        self._tails: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._run_samples = 0
        self._n = 0
        # the current run: its H, Σ_k (J_k + J_(k+d))ᵀ(J_k + J_(k+d)) (d = 1..L), first L samples
        self._run_gram = np.zeros((self.lag + 1, p, p))
        self._head: np.ndarray | None = None

    @property
    def bread(self) -> np.ndarray:
        """H = Σ J_kᵀ J_k over every closed run, (P, P)."""
        return np.asarray(self._gram[0])

    @property
    def grams(self) -> list[np.ndarray]:
        """H, then ``D_d = Σ_k (J_kᵀ J_(k+d) + J_(k+d)ᵀ J_k)`` for d = 1..L, within every
        closed run, (P, P) each."""
        return list(self._gram)

    def merge(self, other: LaggedSums) -> None:
        """Add the closed runs of ``other`` (same H⁻¹ and lag) to these."""
        if other.lag != self.lag or other._gram.shape != self._gram.shape:
            raise UsageError(f"cannot merge sums of lag {other.lag} into sums of lag {self.lag}")
        if self._tails is not None or other._tails is not None:
            raise UsageError("close every run (end_run) before merging")
        self._gram += other._gram
        self._trace += other._trace
        self._q += other._q
        self._count += other._count
        self._n = self._n or other._n

    def add(self, jac: np.ndarray, resid: np.ndarray) -> None:
        """Add the next rows of the current run.

        Parameters
        ----------
        jac
            Whitened Jacobian, (rows, n, P).
        resid
            Whitened residuals, (rows, n).
        """
        j = np.asarray(jac, dtype=float)
        e = np.asarray(resid, dtype=float)
        p = self._h_inv.shape[0]
        if j.ndim != 3 or j.shape[2] != p or e.shape != j.shape[:2]:
            raise UsageError(f"expected (rows, n, {p}) and (rows, n), got {j.shape}, {e.shape}")
        if j.shape[0] == 0:
            return
        if self._head is None:
            self._head = j[: self.lag].copy()
        elif self._head.shape[0] < self.lag:
            self._head = np.concatenate([self._head, j[: self.lag - self._head.shape[0]]])
        # One (rows·n, P) product: a batched (n, P) @ (P, P) matmul is many times slower.
        z = (j.reshape(-1, p) @ self._h_inv).reshape(j.shape)
        if self._tails is not None:
            tj, tz, te = self._tails
            j, z, e = np.concatenate([tj, j]), np.concatenate([tz, z]), np.concatenate([te, e])
            first = tj.shape[0]
        else:
            first = 0
        rows = j.shape[0]
        flat = j.reshape(rows, -1)  # a sample's rows together: sample ranges are contiguous
        total = np.empty((min(rows - first, SUB_BLOCK) * j.shape[1], p))
        for lo in range(first, rows, SUB_BLOCK):
            hi = min(lo + SUB_BLOCK, rows)
            for d in range(2 * self.lag + 1):
                start = max(lo, d)
                if start >= hi:
                    break
                # Pairs (t − d, t) whose later sample t is in [lo, hi).
                later, earlier = slice(start, hi), slice(start - d, hi - d)
                # Row ranges of C-ordered arrays are contiguous: dot products without temporaries.
                if d > self.lag:
                    self._trace[d] += float(np.vdot(z[earlier], j[later]))
                    continue
                self._q[d] += float(np.vdot(e[earlier], e[later]))
                a = flat[earlier].reshape(-1, p)
                if d:
                    a = np.add(a, flat[later].reshape(-1, p), out=total[: a.shape[0]])
                self._run_gram[d] += a.T @ a  # a block times itself: half of a general product
        self._run_samples += rows - first
        keep = min(rows, 2 * self.lag)
        self._tails = (j[rows - keep :], z[rows - keep :], e[rows - keep :]) if keep else None
        self._n = e.shape[1]

    def end_run(self) -> None:
        """Close the current run."""
        if self._run_samples:
            lags = np.arange(self.lag + 1)
            self._count += self._n * np.maximum(self._run_samples - lags, 0)
            h = self._run_gram[0]
            self._gram[0] += h
            if self._head is not None and self._tails is not None:  # (both kept when L > 0)
                # Σ_(k<d) J_kᵀJ_k and Σ_(k≥N−d) J_kᵀJ_k for d = 1..L (all N samples if N < d)
                head = self._head
                tail = self._tails[0][::-1][: self.lag]
                first = np.cumsum(np.einsum("kip,kiq->kpq", head, head), axis=0)
                last = np.cumsum(np.einsum("kip,kiq->kpq", tail, tail), axis=0)
                for d in range(1, self.lag + 1):
                    edges = first[min(d, first.shape[0]) - 1] + last[min(d, last.shape[0]) - 1]
                    self._gram[d] += self._run_gram[d] - 2.0 * h + edges
        self._tails = None
        self._run_samples = 0
        self._run_gram[:] = 0.0
        self._head = None

    def covariance(self) -> tuple[np.ndarray, ErrorAutocovariance]:
        """``H⁻¹ (Jᵀ Ω̂ J) H⁻¹`` with Ω̂ from the bias-corrected autocovariance, (P, P)."""
        lag = self.lag
        h_inv = np.linalg.pinv(self._gram[0], hermitian=True)
        p = h_inv.shape[0]
        if self._count[0] <= p:
            raise UsageError(f"need more equations ({self._count[0]:.0f}) than parameters ({p})")
        # D_d = Jᵀ V_d J and its trace with H⁻¹; D_0 = H.
        gram = self.grams
        # tr(H⁻¹ H), then tr(H⁻¹ D_d) = 2 tr(H⁻¹ G_d) with the given H⁻¹: from the sums for
        # d ≤ L, from the pass's dot products beyond
        tr_h = [float(np.sum(self._h_inv * d)) for d in gram]
        tr_d = np.concatenate([tr_h, 2.0 * self._trace[lag + 1 :]])
        e_mat = [gram[0]] + [0.5 * g for g in gram[1:]]  # Jᵀ U_l J
        hd = [h_inv @ g for g in gram]
        he = [h_inv @ g for g in e_mat]
        a = np.zeros((lag + 1, lag + 1))
        for l in range(lag + 1):
            for m in range(lag + 1):
                if l == 0:
                    t2 = 2.0 * tr_d[m]
                elif m == 0:
                    t2 = tr_d[l]
                else:  # 2 tr(H⁻¹ Jᵀ U_l V_m J), V_l V_m ≈ V_(l+m) + V_|l−m| (V_0 → 2I)
                    near = 2.0 * tr_d[0] if l == m else tr_d[abs(l - m)]
                    t2 = tr_d[l + m] + near
                t4 = float(np.sum(he[l] * hd[m].T))  # tr(H⁻¹ E_l H⁻¹ D_m)
                a[l, m] = (self._count[l] if l == m else 0.0) - t2 + t4
        gamma, meat, tapered = _positive(np.linalg.solve(a, self._q), gram)
        cov = h_inv @ meat @ h_inv
        info = ErrorAutocovariance(
            gamma=gamma,
            long_run=float((gamma[0] + 2.0 * gamma[1:].sum()) / gamma[0]) if gamma[0] else 1.0,
            tapered=tapered,
        )
        return np.asarray(0.5 * (cov + cov.T)), info


def _positive(gamma: np.ndarray, gram: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, bool]:
    """γ whose meat ``Σ γ_m D_m`` is positive semi-definite (as it is, Bartlett weighted, or
    lag 0 only), that meat, and whether γ was changed.

    Why the meat and not the spectral density: decimated errors have almost no power near the
    new Nyquist frequency, so a few estimated lags often give a density slightly below zero
    there; the regressor has no content at those frequencies, and weighting the lags down
    to lift it would shrink the slow content this module exists to measure.
    """
    if gamma[0] <= 0.0:
        # Only residuals at round-off (an exact fit) leave no positive variance: nothing to
        # spread, so no uncertainty, rather than an error the data did not cause.
        zero = np.zeros_like(gamma)
        return zero, np.zeros_like(gram[0]), bool(np.any(gamma != 0.0))

    scale = np.sqrt(np.clip(np.diag(gram[0]), 1e-300, None))

    def meat_of(g: np.ndarray) -> np.ndarray:
        return np.asarray(sum(gm * d for gm, d in zip(g, gram, strict=True)))

    def psd(meat: np.ndarray) -> bool:
        eig = np.linalg.eigvalsh(meat / np.outer(scale, scale))
        return bool(eig.min() >= -PSD_TOL * max(eig.max(), 1e-300))

    meat = meat_of(gamma)
    if psd(meat):
        return gamma, meat, False
    tapered = gamma * (1.0 - np.arange(gamma.size) / gamma.size)
    meat = meat_of(tapered)
    if psd(meat):
        return tapered, meat, True
    white = np.concatenate([gamma[:1], np.zeros(gamma.size - 1)])
    return white, meat_of(white), True
