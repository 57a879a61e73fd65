"""Covariance of an IDIM-WLS fit (Case 2) under the error model of the maximum-likelihood gains.

Why: Case 2 refits the base and payload parameters with the gains ĝ of
:func:`~drivegain.identify.ml.ml_fit`, on runs the gains were identified from. Its Newey-West
sandwich (:func:`~drivegain.identify.cases.case_covariance` without a model) has two faults,
measured on 400 simulated seeds:

- it is too small: the fit removes the slow content of the residuals, where their excess
  variance lives, and the Bartlett weights shrink what is left (payload σ 2-13 % small under
  torque noise, as the gains' own Newey-West σ was before :mod:`.autocov`);
- the gains' share is added as if independent of the fit's noise, but both come from the same
  samples: on the mass of a payload fitted with the unloaded run, the two parts of the error
  are correlated by −0.5 and σ came out 15 % too large.

The model is the one the maximum-likelihood fit estimated. The current errors of sample k are
``r_k = S_k L ẽ_k`` (:class:`~.mlmodel.Whitening`), with ``Cov(ẽ_k, ẽ_(k+m)) = γ_m I``
(γ from :class:`~.autocov.LaggedSums`, corrected for that fit). Case 2's weighted equation
errors are then ``ε_k = Λ⁻¹ K diag(g) r_k`` (Λ = diag(σ_j), K the coupled current matrix), so
with ``A_k`` the fit's weighted rows (n, p):

- the fit's error is ``H⁻¹ Σ_k U_kᵀ ẽ_k``, ``U_k = Lᵀ S_k diag(g) Kᵀ Λ⁻¹ A_k``;
- the gains' error is ``Σ_k V_kᵀ ẽ_k``, ``V_k = J̃_k H_ml⁻¹[:, g]`` on the runs of the gains
  (zero on any other run);

and their joint covariance is ``Σ_k Σ_k' [U V]_kᵀ γ_|k−k'| [U V]_k'`` (:class:`ToeplitzSum`).
Its gains' block is the gains' covariance of the fit itself before the repeat factor, which
the tests check.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivegain.errors import UsageError
from drivegain.identify import forked
from drivegain.identify.design import Design
from drivegain.identify.mlmodel import RunArrays, Whitening, chunks, reversal_of


@dataclass(frozen=True)
class CaseNoise:
    """The maximum-likelihood fit's error model, for the covariance of a fit that uses its gains.

    Attributes
    ----------
    theta
        The fit's unknowns (χ, c, g, χ_uL) (:attr:`~.ml.MLFit.theta`).
    nb
        Unknowns before the gains in ``theta``.
    kt_inv
        K⁻¹, the inverse of the coupled current matrix, (n, n).
    whitening
        Σ̂ and κ̂ of the fit (:class:`~.mlmodel.Whitening`).
    gamma
        γ_0..γ_L of the whitened errors (:attr:`~.autocov.ErrorAutocovariance.gamma`).
    gain_influence
        ``H_ml⁻¹[:, g]``, (P, n): a sample's scores J̃_kᵀẽ_k times it are its share of ĝ − g.
    runs
        The fit's runs as its model read them (:func:`~.mlmodel.run_pair`).
    """

    theta: np.ndarray
    nb: int
    kt_inv: np.ndarray
    whitening: Whitening
    gamma: np.ndarray
    gain_influence: np.ndarray
    runs: tuple[RunArrays, ...]

    @property
    def lag(self) -> int:
        """L, the longest lag of the errors' autocovariance, samples."""
        return int(self.gamma.size - 1)

    @property
    def gains(self) -> np.ndarray:
        """The fit's gains, N·m/A, (n,)."""
        n = self.kt_inv.shape[0]
        return np.asarray(self.theta[self.nb : self.nb + n])

    def run_of(self, d: Design) -> RunArrays | None:
        """The fit's arrays of the run of ``d``, or None when the gains did not use it."""
        for ra in self.runs:
            if ra.regressor is d.run.regressor:
                return ra
        return None


def case_noise(
    theta: np.ndarray,
    nb: int,
    kt: np.ndarray,
    whitening: Whitening,
    gamma: np.ndarray,
    hessian: np.ndarray,
    runs: Sequence[RunArrays],
) -> CaseNoise:
    """:class:`CaseNoise` of a maximum-likelihood fit: θ̂, the number ``nb`` of unknowns
    before the gains, the coupling factor ``kt`` (n, n), the noise model, γ, the fit's H
    (P, P) and its runs."""
    theta = np.asarray(theta, dtype=float)
    n = np.asarray(kt).shape[0]
    h_inv = np.linalg.pinv(np.asarray(hessian, dtype=float), hermitian=True)
    return CaseNoise(
        theta=theta,
        nb=int(nb),
        kt_inv=np.linalg.inv(np.asarray(kt, dtype=float)),
        whitening=whitening,
        gamma=np.asarray(gamma, dtype=float),
        gain_influence=np.asarray(h_inv[:, nb : nb + n]),
        runs=tuple(runs),
    )


class ToeplitzSum:
    """``Σ_k Σ_k' F_kᵀ γ_|k−k'| F_k'`` over runs of per-sample (n, w) blocks F_k, in row blocks.

    Samples of different runs are uncorrelated; within a run the sum is taken as
    ``γ_0 Σ_k F_kᵀF_k + Σ_k (F_kᵀY_k + Y_kᵀF_k)`` with ``Y_k = Σ_(m=1..L) γ_m F_(k−m)``, a
    filter over each sample's L predecessors: one product per block whatever the lag. A block
    needs the run's previous L samples only.

    Parameters
    ----------
    gamma
        γ_0..γ_L (any unit; the sum has it times F's squared).
    width
        w, the columns of F.
    """

    def __init__(self, gamma: np.ndarray, width: int):
        g = np.asarray(gamma, dtype=float)
        if g.ndim != 1 or g.size == 0:
            raise UsageError(f"gamma must be a non-empty vector, got shape {g.shape}")
        self._gamma = g
        self._sum = np.zeros((width, width))
        self._tail: np.ndarray | None = None

    def add(self, block: np.ndarray) -> None:
        """Add the next samples of the current run, (rows, n, w)."""
        f = np.asarray(block, dtype=float)
        if f.ndim != 3 or f.shape[2] != self._sum.shape[0]:
            raise UsageError(f"expected (rows, n, {self._sum.shape[0]}), got {f.shape}")
        rows = f.shape[0]
        if rows == 0:
            return
        lag = self._gamma.size - 1
        ext = f if self._tail is None else np.concatenate([self._tail, f])
        first = ext.shape[0] - rows
        y = np.zeros_like(f)
        for m in range(1, lag + 1):
            # Y_k += γ_m F_(k−m) for the block's samples k whose predecessor m is in the run.
            lo = max(first, m)
            if lo >= ext.shape[0]:
                break
            y[lo - first :] += self._gamma[m] * ext[lo - m : ext.shape[0] - m]
        # Σ F_kᵀ(γ_0/2 F_k + Y_k), plus its transpose: one product per block
        y += 0.5 * self._gamma[0] * f
        self._sum += f.reshape(-1, f.shape[2]).T @ y.reshape(-1, f.shape[2])
        self._tail = ext[-lag:].copy() if lag else None

    def end_run(self) -> None:
        """Close the current run."""
        self._tail = None

    def total(self) -> np.ndarray:
        """The sum over every sample added, (w, w), symmetric."""
        return np.asarray(self._sum + self._sum.T)


def model_sums(
    designs: Sequence[Design],
    transforms: Sequence[np.ndarray],
    sigma: np.ndarray,
    params: int,
    noise: CaseNoise,
    blocks: Sequence[Sequence[slice]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model's sums for a fit of ``params`` unknowns on ``designs``.

    Parameters
    ----------
    designs, transforms, sigma
        The fit's runs, column transforms (the first ``params`` columns are its unknowns) and
        per-joint weights σ_j (N·m), as :func:`~drivegain.identify.cases.case_covariance`.
    params
        p, the fit's unknowns.
    noise
        The gains' error model.
    blocks
        Per design, its row blocks.

    Returns
    -------
    s_uu, s_uv, s_vv
        ``Σ Uᵀ γ U`` (p, p), ``Σ Uᵀ γ V`` (p, n), ``Σ Vᵀ γ V`` (n, n): the fit's meat, its
        covariance with the gains' error times H (the fit's bread), and the gains' covariance.
    """
    n = noise.kt_inv.shape[0]
    items = list(zip(designs, transforms, blocks, strict=True))
    # Long runs: the first in a forked child meanwhile (the same sums either way).
    long = sum(d.rows for d in designs) * n >= forked.PARALLEL_EQUATIONS
    per_run = forked.map_items(
        "Case 2 covariance",
        lambda item: _run_sum(item[0], item[1], item[2], sigma, params, noise),
        items,
        parallel=long,
    )
    s = np.sum(per_run, axis=0)
    return s[:params, :params], s[:params, params:], s[params:, params:]


#: Samples per :meth:`ToeplitzSum.add` in :func:`model_sums`, so that the filter's lagged copies
#: stay in cache (blocks of a few hundred samples and more ran about twice as slow; the whole
#: command's cost is in ``benchmarks/bench_identify.py --baseline-ref``).
SUB_BLOCK = 96


def _run_sum(
    d: Design,
    t: np.ndarray,
    rows: Sequence[slice],
    sigma: np.ndarray,
    params: int,
    noise: CaseNoise,
) -> np.ndarray:
    """:func:`model_sums`' sum of one run, (p + n, p + n)."""
    n = noise.kt_inv.shape[0]
    w = noise.whitening
    chol_t = np.linalg.cholesky(w.noise).T  # Lᵀ
    mix = noise.gains[:, None] * d.kt.T  # diag(g) Kᵀ
    acc = ToeplitzSum(noise.gamma, params + n)
    ra = noise.run_of(d)
    rev = reversal_of(d) if ra is None else ra.reversal
    coefs = None if ra is None else _share_coefficients(noise, ra)
    for sl in rows:
        sub = d.subset(sl)
        # Λ⁻² D_k T (rows, n, p): A_k once more over σ_j
        a = np.stack([sub.block(j) @ t[:, :params] / sigma[j] ** 2 for j in range(n)], 1)
        u = np.matmul(mix, a)
        if rev is not None and np.any(w.kappa != 0.0):
            u *= np.sqrt(1.0 + w.kappa[None, :] * rev[sl])[:, :, None]
        f = np.zeros((a.shape[0], n, params + n))
        f[:, :, :params] = np.matmul(chol_t, u)
        if ra is not None and coefs is not None:
            f[:, :, params:] = _gain_share(noise, ra.rows(sl), coefs)
        # sub-blocks whose lagged copies stay in cache
        for k in range(0, f.shape[0], SUB_BLOCK):
            acc.add(f[k : k + SUB_BLOCK])
    return acc.total()


def _share_coefficients(noise: CaseNoise, ra: RunArrays) -> np.ndarray:
    """Coefficients of the regressor's columns, (c, n + 1): per gain, the columns' share of
    ``W G`` (G = :attr:`CaseNoise.gain_influence`), then θ's (the model torque)."""
    n, nb = noise.kt_inv.shape[0], noise.nb
    g = noise.gain_influence
    out = np.zeros((ra.regressor.c, n + 1))
    # add.at: a column of the payload's link may also be a base column
    np.add.at(out, ra.base_idx, np.column_stack([g[:nb], noise.theta[:nb]]))
    if ra.unknown_idx is not None:
        chi_u = noise.theta[nb + n :]
        np.add.at(out, ra.unknown_idx, np.column_stack([g[nb + n :], chi_u]))
    if ra.known_idx is not None:
        np.add.at(out[:, n], ra.known_idx, ra.known_values)
    return out


def _gain_share(noise: CaseNoise, ra: RunArrays, coefs: np.ndarray) -> np.ndarray:
    """``V_k = J̃_k G`` of the samples of ``ra``, (rows, n, n), without the whole Jacobian."""
    return _share_and_currents(noise, ra, coefs)[0]


def _share_and_currents(
    noise: CaseNoise, ra: RunArrays, coefs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``V_k = J̃_k G`` of the samples of ``ra``, (rows, n, n), and the model currents v̂_k
    (A, (rows, n)).

    ``∂v̂_k/∂θ · G = M (W_k G_χ + W_u,k G_u) − diag(v̂_k/g) G_g`` with ``M = diag(1/g) K⁻¹``:
    the regressor's series times ``coefs`` (:func:`_share_coefficients`) give ``W G`` and the
    model torque in one product, then the fit's whitening.
    """
    n, nb = noise.kt_inv.shape[0], noise.nb
    g = noise.gains
    both = ra.regressor.dot(coefs)  # (rows, n, n + 1)
    m = noise.kt_inv / g[:, None]
    v_hat = both[:, :, n] @ m.T
    share = np.matmul(m, both[:, :, :n])
    share -= (v_hat / g[None, :])[:, :, None] * noise.gain_influence[nb : nb + n][None, :, :]
    return noise.whitening.apply(share, ra.reversal), v_hat


def gain_scores(noise: CaseNoise, d: Design) -> np.ndarray | None:
    """Each sample's share of the gains' error, as its own residuals show it.

    To first order ĝ − g = Σ_k V_kᵀ ẽ_k over the samples of the gains' runs (the module
    docstring); with the fit's whitened residuals in place of the errors, φ_k = V_kᵀ ẽ_k. A
    fit whose covariance reads its own residuals (Newey-West) gets its correlation with the
    gains' error from the lagged products of its scores with these, as it gets its own
    variance from its scores alone (:func:`~drivegain.identify.cases.case_covariance`).

    Parameters
    ----------
    noise
        The gains' error model.
    d
        A design of one of the runs (any row weights: the gains used every entry).

    Returns
    -------
    numpy.ndarray or None
        φ, N·m/A, (N, n), per sample and gain; None when the gains did not use the run.
    """
    ra = noise.run_of(d)
    if ra is None:
        return None
    coefs = _share_coefficients(noise, ra)
    out = np.empty((ra.samples, noise.kt_inv.shape[0]))
    for sl in chunks(ra.samples):
        sub = ra.rows(sl)
        share, v_hat = _share_and_currents(noise, sub, coefs)
        resid = noise.whitening.apply(sub.v - v_hat, sub.reversal)
        out[sl] = np.matmul(resid[:, None, :], share)[:, 0, :]
    return out
