"""The measurement model of the maximum-likelihood gains (:mod:`.ml`), evaluated in row blocks.

For every sample k of a run, the model currents of the n drives are
``v̂_k = diag(1/g) · K⁻¹ · (W_k χ + W_uL,k χ_uL + W_kL,k χ_kL)`` with θ = (χ, g, χ_uL). This module
holds a run's arrays as the model reads them (:class:`RunArrays`), the model's currents
(:func:`predict`), its Jacobian (:func:`jacobian`), the whitened Jacobian and residuals of a row
block (:func:`whitened_block`) with their per-sample scores, and the rows of the least squares
with V as regressor (:func:`ls_rows`). Long runs are evaluated :data:`CHUNK` samples at a time:
the gathered regressor columns and the Jacobian exist for one block at a time.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from drivegain.config.payload import Payload
from drivegain.identify.compact import CompactRegressor
from drivegain.identify.design import Design

#: Samples per row block when building factors and scores (bounds the memory of long runs).
CHUNK = 2048


@dataclass(frozen=True)
class RunArrays:
    """One run's data as the ML model uses it, read from the prepared run's regressor.

    Nothing of the size of the regressor is copied here: :attr:`w`, :attr:`wu` and
    :attr:`tau_known` are gathered when asked for, meant for row blocks (:meth:`rows`).

    Attributes
    ----------
    v
        Currents, A, (N, n).
    regressor
        The prepared run's regressor columns, (N, n, c) (the same object, not a copy).
    base_idx
        Its columns of the base parameters, then of the reversal Coulomb coefficients
        (:func:`run_arrays`'s ``coulomb``); the model's χ is the coefficients of all of them.
    unknown_idx
        Its columns of the unknown payload parameters, (nu,); None for the unloaded run
        (whose payload columns are zero).
    known_idx, known_values
        Its columns of the known payload parameters and their values (None when unloaded).
    nu
        Number of unknown payload parameters.
    reversal
        (N, n): each entry's share of reversal, the share of its filter window near a reversal
        of a Coulomb term of its drive (:mod:`.reversals`), 0-1; its variance grows with it
        (:class:`Whitening`). None when no entry has any.
    """

    v: np.ndarray
    regressor: CompactRegressor
    base_idx: np.ndarray
    unknown_idx: np.ndarray | None
    known_idx: np.ndarray | None
    known_values: np.ndarray
    nu: int
    reversal: np.ndarray | None = None

    @property
    def samples(self) -> int:
        return int(self.v.shape[0])

    @property
    def w(self) -> np.ndarray:
        """Base-parameter regressor per joint, (N, n, nb) (a copy: use on row blocks)."""
        return self.regressor.gather(self.base_idx)

    @property
    def wu(self) -> np.ndarray:
        """Unknown payload parameters' columns per joint, (N, n, nu) (zero when unloaded)."""
        if self.unknown_idx is None:
            return np.zeros((self.samples, self.v.shape[1], self.nu))
        return self.regressor.gather(self.unknown_idx)

    @property
    def tau_known(self) -> np.ndarray:
        """Torque of the known payload parameters, N·m, (N, n) (zero when unloaded)."""
        if self.known_idx is None:
            return np.zeros((self.samples, self.v.shape[1]))
        return np.asarray(self.regressor.gather(self.known_idx) @ self.known_values)

    def rows(self, sl: slice) -> RunArrays:
        """The samples ``sl`` (views, no copy)."""
        rev = None if self.reversal is None else self.reversal[sl]
        return replace(self, v=self.v[sl], regressor=self.regressor.rows(sl), reversal=rev)


def reversal_of(d: Design) -> np.ndarray | None:
    """Each entry's share of reversal (:attr:`RunArrays.reversal`) of the run of ``d``, 0-1,
    (N, n); None when no entry has any."""
    if d.run.reversal_share is None:
        return None
    rev = np.clip(np.abs(d.run.reversal_share), 0.0, 1.0)
    return rev if rev.any() else None


def run_arrays(
    d: Design, payload: Payload, reversals: bool = True, coulomb: np.ndarray | None = None
) -> RunArrays:
    """The ML model's view of a design (:class:`RunArrays`).

    Parameters
    ----------
    d
        The design of one run.
    payload
        The payload of the loaded run, whose ``known`` parameters fix the scale; an unloaded
        design gets zero payload columns of the same shape.
    reversals
        Give the entries their share of reversal (:attr:`RunArrays.reversal`) when the run
        has it (False: every entry the same variance, as the fit was first built).
    coulomb
        The reversal Coulomb columns of the run's regressor estimated after the base
        parameters (:attr:`~.prepare.PreparedRun.reversal_coulomb`; None: the run's own, empty:
        none). Two runs fitted together need the same (:func:`run_pair`).
    """
    rev = reversal_of(d) if reversals else None
    mask = payload.known_mask()
    unknown = np.flatnonzero(~mask)
    unknown_idx = known_idx = None
    if d.payload_idx is not None:
        unknown_idx = d.payload_idx[unknown]
        known_idx = d.payload_idx[mask]
    cols = d.run.reversal_coulomb if coulomb is None else coulomb
    base_idx = np.asarray(d.base_idx)
    if cols is not None and len(cols):
        base_idx = np.concatenate([base_idx, np.asarray(cols, dtype=base_idx.dtype)])
    return RunArrays(
        v=np.asarray(d.run.current, float),
        regressor=d.run.regressor,
        base_idx=base_idx,
        unknown_idx=unknown_idx,
        known_idx=known_idx,
        known_values=np.asarray(payload.values[mask], float),
        nu=int(unknown.size),
        reversal=rev,
    )


def run_pair(a: Design, b: Design, payload: Payload, reversals: bool = True) -> list[RunArrays]:
    """``[run_arrays(a), run_arrays(b)]`` with one θ: the reversal Coulomb columns of either
    run (a run without one of them has a zero column there)."""
    own = [d.run.reversal_coulomb for d in (a, b) if d.run.reversal_coulomb is not None]
    cols = np.unique(np.concatenate(own)) if own else np.empty(0, dtype=np.intp)
    return [run_arrays(d, payload, reversals, cols) for d in (a, b)]


@dataclass(frozen=True)
class Whitening:
    """The noise model as the fit applies it: e_k ↦ L⁻¹ S_k⁻¹ e_k.

    Σ = L Lᵀ (A², (n, n)) is the covariance of the current errors of an entry away from
    reversals. S_k is diagonal, √(1 + κ_i s_ki) for drive i, s_ki the entry's share of reversal
    (:attr:`RunArrays.reversal`): the entries near reversals of a drive's Coulomb terms have
    (1 + κ_i s) times the variance (:mod:`.reversals`).

    Attributes
    ----------
    noise
        Σ, A², (n, n).
    kappa
        κ, ≥ 0, (n,): the variance added per unit share of reversal, relative to Σ_ii.
    """

    noise: np.ndarray
    kappa: np.ndarray

    @functools.cached_property
    def matrix(self) -> np.ndarray:
        """L⁻¹, (n, n)."""
        return np.asarray(np.linalg.inv(np.linalg.cholesky(self.noise)))

    def apply(self, x: np.ndarray, reversal: np.ndarray | None) -> np.ndarray:
        """Whitened ``x``, (N, n) or (N, n, P), of entries with the shares of reversal
        ``reversal`` ((N, n), or None for none)."""
        x = unscaled(x, reversal, self.kappa)
        if x.ndim == 2:
            return np.asarray(x @ self.matrix.T)
        return np.asarray(self.matrix @ x)


def unscaled(x: np.ndarray, reversal: np.ndarray | None, kappa: np.ndarray) -> np.ndarray:
    """S_k⁻¹ x_k (:class:`Whitening`) of (N, n) or (N, n, P) ``x``: each entry divided by
    √(1 + κ_i s); ``x`` itself when no entry is scaled."""
    if reversal is None or not np.any(kappa != 0.0):
        return x
    s = 1.0 / np.sqrt(1.0 + kappa[None, :] * reversal)
    return x * (s if x.ndim == 2 else s[:, :, None])


def split_theta(theta: np.ndarray, nb: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return theta[:nb], theta[nb : nb + n], theta[nb + n :]


def predict(theta: np.ndarray, run: RunArrays, kt_inv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Model currents v̂ (A, (N, n)) and the model torques mapped by K⁻¹ (N·m, (N, n)).

    Evaluated in row blocks of :data:`CHUNK` samples: the gathered columns W, W_uL exist for
    one block at a time.
    """
    nb, n = run.base_idx.size, run.v.shape[1]
    g = theta[nb : nb + n]
    u = np.empty((run.samples, n))
    for sl in chunks(run.samples):
        sub = run.rows(sl)
        u[sl] = _torque(theta, sub, sub.w) @ kt_inv.T
    return u / g[None, :], u


def _torque(theta: np.ndarray, run: RunArrays, w: np.ndarray) -> np.ndarray:
    """Model torques W χ + W_uL χ_uL + τ_kL of ``run``, N·m, (N, n); ``w`` is ``run.w``."""
    chi, _, chi_u = split_theta(theta, run.base_idx.size, run.v.shape[1])
    tau = w @ chi + run.tau_known
    if chi_u.size:
        tau = tau + run.wu @ chi_u
    return np.asarray(tau)


def jacobian(
    theta: np.ndarray,
    run: RunArrays,
    kt_inv: np.ndarray,
    v_hat: np.ndarray | None = None,
    w: np.ndarray | None = None,
) -> np.ndarray:
    """∂v̂/∂θ per sample, (N, n, P), θ = (χ, g, χ_uL); ``v_hat``: :func:`predict`'s currents
    at θ and ``w``: ``run.w``, when the caller has them (computed here otherwise)."""
    nb, n = run.base_idx.size, run.v.shape[1]
    g = theta[nb : nb + n]
    m = kt_inv / g[:, None]  # diag(1/g) K⁻¹
    if v_hat is None:
        v_hat, _ = predict(theta, run, kt_inv)
    jac = np.zeros((run.samples, n, theta.size))
    jac[:, :, :nb] = m @ (run.w if w is None else w)  # batched over samples
    idx = np.arange(n)
    jac[:, idx, nb + idx] = -v_hat / g[None, :]
    if theta.size > nb + n:
        jac[:, :, nb + n :] = m @ run.wu
    return jac


def ls_rows(run: RunArrays, kt: np.ndarray) -> np.ndarray:
    """Rows ``[−W | V K | −W_uL]`` of the least squares with V as regressor, (N, n, P).

    Their product with θ = (χ, g, χ_uL) minus the known payload's torque is the equation error
    of every sample and joint, N·m.
    """
    nb, n, nu = run.base_idx.size, run.v.shape[1], run.nu
    m = np.zeros((run.samples, n, nb + n + nu))
    m[:, :, :nb] = -run.w
    m[:, :, nb : nb + n] = run.v[:, None, :] * kt[None, :, :]
    m[:, :, nb + n :] = -run.wu
    return m


def chunks(samples: int) -> list[slice]:
    """Row blocks of :data:`CHUNK` samples covering ``samples``."""
    return [slice(k, min(k + CHUNK, samples)) for k in range(0, samples, CHUNK)]


def whitened_block(
    theta: np.ndarray, run: RunArrays, kt_inv: np.ndarray, whiten: Whitening
) -> tuple[np.ndarray, np.ndarray]:
    """Whitened Jacobian J̃_k = L⁻¹ ∂v̂_k/∂θ, (N, n, P), and residuals ẽ_k, (N, n), of ``run``.

    Meant for row blocks (:func:`chunks`): the Jacobian is the largest array of the fit, and
    the block's columns W are gathered once for the currents and the Jacobian.
    """
    nb, n = run.base_idx.size, run.v.shape[1]
    w = run.w
    v_hat = (_torque(theta, run, w) @ kt_inv.T) / theta[nb : nb + n][None, :]
    jw = whiten.apply(jacobian(theta, run, kt_inv, v_hat, w), run.reversal)
    return jw, whiten.apply(run.v - v_hat, run.reversal)


def scores(jw: np.ndarray, ew: np.ndarray) -> np.ndarray:
    """Per-sample scores ψ_k = J̃_kᵀ ẽ_k, (N, P): θ̂ − θ ≈ H⁻¹ Σ_k ψ_k to first order."""
    return np.asarray(np.matmul(ew[:, None, :], jw)[:, 0, :])


def neg_log_lik(
    runs: Sequence[RunArrays], whiten: Whitening, gram: np.ndarray, samples: int
) -> float:
    """−2 log L per sample of a fitted noise model, less its constant n·log 2π.

    Entry k's errors are N(0, S_k Σ S_k): −2 log L = Σ_k [log det Σ + 2 Σ_i log S_ki +
    ε_kᵀ Σ⁻¹ ε_k], ε_k = S_k⁻¹ e_k, whose Gram the fit holds (``gram``). Fits of the same
    currents (the same entries) compare by it whatever their regressor columns.

    Parameters
    ----------
    runs
        The runs fitted (their reversal shares).
    whiten
        Σ̂ (A²) and κ̂ of the fit.
    gram
        Σ_k ε_k ε_kᵀ of the fit's residuals scaled by S_k⁻¹, A², (n, n).
    samples
        Entries in the sums (samples of all runs).
    """
    sigma = np.asarray(whiten.noise, float)
    logdet = float(np.linalg.slogdet(sigma)[1])
    quad = float(np.trace(np.linalg.solve(sigma, gram)))
    scale = sum(
        float(np.sum(np.log1p(whiten.kappa * r.reversal))) for r in runs if r.reversal is not None
    )
    return logdet + (quad + scale) / samples
