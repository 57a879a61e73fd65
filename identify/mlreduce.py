"""The Gauss-Newton steps of the maximum-likelihood gains (:mod:`.ml`) on runs reduced once.

At every sample k, the scaled residuals ε_k = S_k⁻¹ (v_k − v̂_k) of the model of :mod:`.ml`, their
derivatives with respect to θ = (χ, g, χ_uL) and hence the whitened residuals and Jacobian
``ẽ_k = L⁻¹ ε_k``, ``J̃_k = L⁻¹ S_k⁻¹ ∂v̂_k/∂θ`` are linear in one data vector d_k: for each drive i,
its current and the regressor series of the joints whose torques reach it through K⁻¹, all times
drive i's S_k⁻¹ entry 1/√(1 + κ_i s_ki). Only the coefficients depend on θ and Σ. So a run is
reduced once per κ to the R factor of its data matrix D (``RᵀR = DᵀD``, Householder in row
blocks), and every step works on R: ``‖D a‖ = ‖R a‖`` for any coefficients a, and the R factor
of ``[J̃ | ẽ]`` is that of ``R [B_m | a_m]`` stacked over the whitened rows m.

It is the same least squares to round-off: Householder QR is backward stable column by column,
so nothing is squared, unlike normal equations. A step costs a few small matrix products instead
of a pass over the samples, and so does each trial of the line search; a fit costs one pass per
value of κ (two: κ = 0, then the estimated κ).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivegain.errors import UsageError
from drivegain.identify.estimate import r_factor
from drivegain.identify.mlmodel import RunArrays, Whitening

__all__ = ["ReducedRun", "augmented_factor", "reduce_run", "residual_gram", "whitened_sq"]

#: Samples per row block of the reduction (the block and its R factor are reduced together).
#: The block, its stack with R and the QR's copy of that stack are the main process's largest
#: transient arrays while a run is reduced (~9 MB each here for a 6-axis run). 8192 samples cost
#: the 2 × 10-minute, 1 kHz case 22 MB more peak memory (489 against 467 MB) for 1 % less CPU.
BLOCK = 4096


@dataclass(frozen=True)
class _Block:
    """The columns of d_k that carry joint ``joint``'s series for drive ``row``.

    ``series`` index the run's regressor series, ``phi`` their parameters in φ = (χ, χ_uL);
    ``known`` is the column of the known payload torque τ_kL of that joint (-1: none), which
    is Σ series[known_series] · known_values.
    """

    row: int
    joint: int
    start: int
    series: np.ndarray
    phi: np.ndarray
    known: int
    known_series: np.ndarray
    known_values: np.ndarray


@dataclass(frozen=True)
class Layout:
    """Where everything stands in a run's data vector d_k (:func:`layout`): its length
    ``size``, the column of each drive's current ``current`` (n,), the drive whose S_k⁻¹ entry
    scales each column ``owner`` (size,), and the regressor columns ``blocks``, one per (drive,
    joint whose torque reaches it).
    """

    size: int
    current: np.ndarray
    owner: np.ndarray
    blocks: tuple[_Block, ...]

    @property
    def own(self) -> list[np.ndarray]:
        """The columns of each drive, n arrays."""
        return [np.flatnonzero(self.owner == i) for i in range(self.current.size)]


@dataclass(frozen=True)
class ReducedRun:
    """A run reduced at one κ: ``factor`` is the R of its data matrix D, (size, size)."""

    layout: Layout
    factor: np.ndarray
    kappa: np.ndarray
    samples: int


def layout(run: RunArrays, kt_inv: np.ndarray) -> Layout:
    """The data vector of ``run``: per drive i, its current, then for each joint j with
    (K⁻¹)_ij ≠ 0 the series of j's row among the base and unknown payload columns, and j's
    known payload torque if the run has one."""
    n = run.v.shape[1]
    reg = run.regressor
    unknown = np.empty(0, dtype=np.intp) if run.unknown_idx is None else run.unknown_idx
    jj, pp, ss = reg.entries(np.concatenate([run.base_idx, unknown]).astype(np.intp))
    kj = kp = ks = np.empty(0, dtype=np.intp)
    if run.known_idx is not None:
        kj, kp, ks = reg.entries(run.known_idx)
    current = np.empty(n, dtype=np.intp)
    owner: list[int] = []
    blocks: list[_Block] = []
    for i in range(n):
        current[i] = len(owner)
        owner.append(i)
        for j in np.flatnonzero(kt_inv[i] != 0.0):
            mine = jj == j
            start = len(owner)
            owner.extend([i] * int(mine.sum()))
            known = -1
            theirs = kj == j
            if theirs.any():
                known = len(owner)
                owner.append(i)
            blocks.append(
                _Block(
                    row=i,
                    joint=int(j),
                    start=start,
                    series=ss[mine],
                    phi=pp[mine],  # positions in [base_idx, unknown_idx] are those in φ
                    known=known,
                    known_series=ks[theirs],
                    known_values=np.asarray(run.known_values, float)[kp[theirs]],
                )
            )
    return Layout(len(owner), current, np.asarray(owner, dtype=np.intp), tuple(blocks))


def data_rows(run: RunArrays, lay: Layout, kappa: np.ndarray, sl: slice) -> np.ndarray:
    """The rows d_k of the samples ``sl``, (rows, size)."""
    sub = run.rows(sl)
    ser = sub.regressor.series
    d = np.empty((sub.samples, lay.size))
    d[:, lay.current] = sub.v
    for b in lay.blocks:
        d[:, b.start : b.start + b.series.size] = ser[:, b.series]
        if b.known >= 0:
            d[:, b.known] = ser[:, b.known_series] @ b.known_values
    if sub.reversal is not None and np.any(kappa != 0.0):
        s = 1.0 / np.sqrt(1.0 + kappa[None, :] * sub.reversal)
        d *= s[:, lay.owner]
    return d


def reduce_run(run: RunArrays, kt_inv: np.ndarray, kappa: np.ndarray) -> ReducedRun:
    """``run`` reduced at ``kappa`` (one pass over its samples in blocks of :data:`BLOCK`)."""
    lay = layout(run, kt_inv)
    kappa = np.asarray(kappa, float)
    r = np.zeros((lay.size, lay.size))
    for k in range(0, run.samples, BLOCK):
        block = data_rows(run, lay, kappa, slice(k, min(k + BLOCK, run.samples)))
        r = r_factor(np.vstack([r, block]))
    return ReducedRun(lay, r, kappa, run.samples)


def coefficients(
    lay: Layout, theta: np.ndarray, nb: int, n: int, kt_inv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients of the scaled residuals and of the model's derivatives at ``theta``.

    Returns
    -------
    c
        (size, n): ε_k = d_k c.
    b
        (n, size, P): drive i's ∂(S_k⁻¹ v̂_k)_i/∂θ = d_k b[i].
    """
    g = theta[nb : nb + n]
    if np.any(g == 0.0):
        raise UsageError("a gain is zero: the model's currents are not defined")
    phi = np.concatenate([theta[:nb], theta[nb + n :]])
    to_theta = np.concatenate([np.arange(nb), np.arange(nb + n, theta.size)])
    c = np.zeros((lay.size, n))
    b = np.zeros((n, lay.size, theta.size))
    c[lay.current, np.arange(n)] = 1.0
    for blk in lay.blocks:
        f = kt_inv[blk.row, blk.joint] / g[blk.row]
        cols = blk.start + np.arange(blk.series.size)
        c[cols, blk.row] = -f * phi[blk.phi]
        b[blk.row, cols, to_theta[blk.phi]] = f
        if blk.known >= 0:
            c[blk.known, blk.row] = -f
    # ∂v̂_i/∂g_i = −v̂_i/g_i, and v̂_i's coefficients are c's without the current, negated
    for i in range(n):
        y = -c[:, i].copy()
        y[lay.current[i]] = 0.0
        b[i, :, nb + i] = -y / g[i]
    return c, b


def residual_gram(
    reduced: Sequence[ReducedRun], theta: np.ndarray, nb: int, kt_inv: np.ndarray
) -> np.ndarray:
    """Σ_k ε_k ε_kᵀ over the runs at ``theta``, A², (n, n) (Σ̂ times the sample count)."""
    n = kt_inv.shape[0]
    out = np.zeros((n, n))
    for red in reduced:
        rc = red.factor @ coefficients(red.layout, theta, nb, n, kt_inv)[0]
        out += rc.T @ rc
    return out


def whitened_sq(gram: np.ndarray, whiten: Whitening) -> float:
    """Σ_k ‖ẽ_k‖² = tr(L⁻¹ G L⁻ᵀ) from ``gram`` G, :func:`residual_gram` of runs reduced at
    ``whiten.kappa``."""
    return float(np.sum(whiten.matrix @ gram * whiten.matrix))


def augmented_factor(
    reduced: Sequence[ReducedRun], theta: np.ndarray, nb: int, kt_inv: np.ndarray, whiten: Whitening
) -> np.ndarray:
    """R factor of ``[J̃ | ẽ]`` over the runs at ``theta``, (P + 1, P + 1).

    ``RᵀR = [J̃ | ẽ]ᵀ[J̃ | ẽ]`` with J̃ the whitened Jacobian of the model's currents and ẽ the
    whitened residuals, as if built from every sample (the runs reduced at ``whiten.kappa``).
    """
    n = kt_inv.shape[0]
    l_inv = whiten.matrix
    parts = []
    for red in reduced:
        if not np.array_equal(red.kappa, whiten.kappa):
            raise UsageError("the runs were reduced at another κ than the whitening's")
        c, b = coefficients(red.layout, theta, nb, n, kt_inv)
        rc = red.factor @ c  # (size, n)
        # R b_i for each drive i; b_i has rows only in drive i's columns of d
        rb = np.stack([red.factor[:, cols] @ b[i, cols] for i, cols in enumerate(red.layout.own)])
        jw = np.tensordot(l_inv, rb, axes=(1, 0))  # whitened row m: Σ_i (L⁻¹)_mi R b_i
        ew = l_inv @ rc.T
        parts.append(np.concatenate([jw, ew[:, :, None]], axis=2).reshape(-1, theta.size + 1))
    return r_factor(np.vstack(parts))
