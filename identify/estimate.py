"""Least-squares estimators of the IDIM: OLS, WLS (eq. 6-11) and weighted TLS (eq. 15-19).

Plain functions on numpy arrays. Everything works from the triangular factor R of a QR
decomposition (``RᵀR = AᵀA``, computed by Householder reflections, never by forming AᵀA):

- a tall matrix A is reduced once to R; stacking the R factors of row blocks and reducing again
  gives the R of the stacked rows, so row weights (one scale per block) and column weights or
  combinations (a right factor T: ``(A T)`` has factor ``R T`` up to an orthogonal transform) are
  applied to small matrices;
- LS solutions and covariances come from R by triangular solves (eq. 7-10);
- the TLS solution is the right singular vector of R for its smallest singular value.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from drivegain.errors import IdentificationError, UsageError

#: A column whose distance to the span of the previous ones is below this fraction of its norm
#: is taken as dependent (cond ~ 1e10 is far beyond anything an identification can use).
DEPENDENT_TOL = 1e-10


def r_factor(a: np.ndarray) -> np.ndarray:
    """Upper-triangular R (k×k) of a (rows×k) matrix: ``RᵀR = AᵀA``.

    Rows fewer than columns are padded with zero rows, so blocks always stack.
    """
    a = np.asarray(a, dtype=float)
    if a.ndim != 2:
        # Programming error of the caller, not user data.
        raise UsageError(f"expected a 2-D matrix, got shape {a.shape}")
    rows, k = a.shape
    if rows == 0:
        return np.zeros((k, k))
    r: np.ndarray = np.asarray(np.linalg.qr(a, mode="r"))
    if r.shape[0] < k:
        r = np.vstack([r, np.zeros((k - r.shape[0], k))])
    return np.asarray(r)


def stacked_factor(blocks: Sequence[np.ndarray]) -> np.ndarray:
    """R factor of the row-wise stack of ``blocks`` (each a matrix or an R factor)."""
    return r_factor(np.vstack(list(blocks)))


@dataclass(frozen=True)
class LSResult:
    """A (weighted) least-squares solution with eq. (8)-(11) statistics.

    Attributes
    ----------
    x
        Solution.
    std
        Standard deviations σ_x (eq. 10), same units as ``x``.
    cov
        Covariance matrix σ̂²·(WᵀW)⁻¹, computed as σ̂²·R⁻¹R⁻ᵀ.
    residual_norm
        ‖Y − W x‖ of the system solved (weighted when rows were weighted).
    sigma
        σ̂_ρ = ‖Y − W x‖ / √(r − b) (eq. 9).
    rows
        r, number of equations.
    """

    x: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    residual_norm: float
    sigma: float
    rows: int

    @property
    def rel_std_percent(self) -> np.ndarray:
        """%σ = 100·σ/|x| (eq. 11); infinite where x is 0."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.x != 0.0, 100.0 * self.std / np.abs(self.x), np.inf)


def dependent_columns(r: np.ndarray, tol: float = DEPENDENT_TOL) -> np.ndarray:
    """Indices of columns of R that are (numerically) combinations of the columns before them.

    For a QR factor, ``|R[k, k]|`` is the distance of column k of A to the span of columns
    0..k-1 and ``‖R[:, k]‖`` its norm, so their ratio measures the dependence directly.
    """
    norms = np.linalg.norm(r, axis=0)
    diag = np.abs(np.diag(r))
    return np.flatnonzero(diag <= tol * np.maximum(norms, np.finfo(float).tiny))


def ls_from_factor(
    r: np.ndarray, rows: int, names: Sequence[str] | None = None, what: str = "parameters"
) -> LSResult:
    """Least-squares solution from the R factor of the augmented matrix ``[W | Y]``.

    Parameters
    ----------
    r
        (k+1, k+1) upper-triangular factor of ``[W | Y]``.
    rows
        Number of equations r (for eq. 9).
    names
        Parameter names, for the error message when the data do not determine one.
    what
        Word for the unknowns in error messages.

    Raises
    ------
    IdentificationError
        A parameter is not determined by the data, or there are no more equations than unknowns.
    """
    k = r.shape[1] - 1
    r11 = r[:k, :k]
    dep = dependent_columns(r11)
    if dep.size:
        label = ", ".join(names[i] for i in dep[:8]) if names else ", ".join(map(str, dep[:8]))
        raise IdentificationError(
            f"the data do not determine the {what} {label}"
            f"{' ...' if dep.size > 8 else ''} (columns dependent on the others: excite more)"
        )
    dof = rows - k
    if dof <= 0:
        raise IdentificationError(f"{rows} equations for {k} unknowns: record more samples")
    x = scipy.linalg.solve_triangular(r11, r[:k, k])
    rho = float(np.linalg.norm(r[k:, k]))
    sigma = rho / np.sqrt(dof)
    rinv = scipy.linalg.solve_triangular(r11, np.eye(k))
    cov = sigma**2 * (rinv @ rinv.T)
    std = sigma * np.linalg.norm(rinv, axis=1)
    return LSResult(x=x, std=std, cov=cov, residual_norm=rho, sigma=sigma, rows=int(rows))


def ols(w: np.ndarray, y: np.ndarray, names: Sequence[str] | None = None) -> LSResult:
    """IDIM-OLS: ``Y = W x + ρ`` solved through a QR factorisation of W (eq. 7-11)."""
    w = np.asarray(w, dtype=float)
    y = np.asarray(y, dtype=float).reshape(-1, 1)
    if w.shape[0] != y.shape[0]:
        # Programming error of the caller, not user data.
        raise UsageError(f"W has {w.shape[0]} rows, Y {y.shape[0]}")
    return ls_from_factor(r_factor(np.hstack([w, y])), w.shape[0], names)


def wls(
    w: np.ndarray,
    y: np.ndarray,
    groups: np.ndarray,
    sigma: np.ndarray,
    names: Sequence[str] | None = None,
) -> LSResult:
    """IDIM-WLS: rows of group g (a joint) weighted by 1/σ_g, then OLS (Gautier 1997).

    ``std`` and ``cov`` are those of x (the weighting does not change x's units); the residual
    norm and σ̂ are those of the weighted system (σ̂ ≈ 1 when the σ_g are right).
    """
    groups = np.asarray(groups)
    weights = 1.0 / np.asarray(sigma, dtype=float)[groups]
    return ols(np.asarray(w) * weights[:, None], np.asarray(y) * weights, names)


@dataclass(frozen=True)
class GroupFit:
    """Per-group OLS fit used to weight rows: σ̂ (eq. 9) of the group's own equations."""

    sigma: float
    residual_norm: float
    rows: int
    rank: int


def group_sigma_from_factor(r: np.ndarray, rows: int) -> GroupFit:
    """σ̂ of an OLS fit of one group of equations, from the R factor of its ``[W | Y]``.

    Columns that are zero in this group (parameters that do not act on this joint) and
    combinations that the group alone cannot separate are handled by a rank-revealing
    least-squares solve; σ̂² = ‖ρ‖² / (r − rank).
    """
    k = r.shape[1] - 1
    x_part = r[:, :k]
    norms = np.linalg.norm(x_part, axis=0)
    keep = norms > DEPENDENT_TOL * max(float(norms.max(initial=0.0)), np.finfo(float).tiny)
    a = x_part[:, keep] / norms[keep]
    sol, _, rank, _ = np.linalg.lstsq(a, r[:, k], rcond=1e-10)
    rho = float(np.linalg.norm(a @ sol - r[:, k]))
    dof = rows - int(rank)
    if dof <= 0:
        raise IdentificationError(
            f"{rows} equations for {rank} parameters on one joint: record more samples"
        )
    return GroupFit(sigma=rho / np.sqrt(dof), residual_norm=rho, rows=int(rows), rank=int(rank))


@dataclass(frozen=True)
class TLSResult:
    """Total least-squares solution of ``A x ≈ 0`` scaled so that its last component is 1.

    Attributes
    ----------
    x
        Solution with ``x[-1] == 1`` (δ of eq. 15).
    vector
        The unit right singular vector it was scaled from.
    singular_values
        Singular values of A, decreasing.
    delta_component
        ``|vector[-1]|``: near zero means the scale (the known payload) is not seen by the data.
    gap
        s_{k-1}/s_k ≥ 1: the ratio of the two smallest singular values. Near 1 the smallest
        singular direction, hence the solution, is ill-determined.
    r_theta
        R factor of A without the last column (the leading block of R), for the covariance.
    """

    x: np.ndarray
    vector: np.ndarray
    singular_values: np.ndarray
    delta_component: float
    gap: float
    r_theta: np.ndarray

    @property
    def lam(self) -> float:
        """s_k², the minimum of ‖A x‖²/‖x‖²."""
        return float(self.singular_values[-1] ** 2)

    @property
    def theta_smin(self) -> float:
        """Smallest singular value of A without its last column.

        A unique TLS solution with δ ≠ 0 needs ``theta_smin > s_k`` (Golub & Van Loan); the
        margin says how far the problem is from having none.
        """
        if self.r_theta.size == 0:
            return float("inf")
        return float(np.linalg.svd(self.r_theta, compute_uv=False)[-1])


#: |δ| in the unit singular vector below which the TLS problem has no finite-scale solution.
DELTA_TOL = 1e-13


class ScaleError(IdentificationError):
    """The smallest right singular vector has (numerically) no component on the δ column.

    This says only that the TLS solution at this column weighting has no finite scale. It has
    two causes that the caller tells apart: the known payload columns are not seen by the data
    (then every weighting fails), or the weighting itself pushes δ below round-off (a V-column
    weight α so small that g/α dwarfs δ = 1; other α solve).

    Attributes
    ----------
    delta
        |δ| of the unit singular vector.
    """

    def __init__(self, delta: float):
        self.delta = delta
        super().__init__(
            f"no TLS solution with a finite scale at this column weighting: the smallest "
            f"singular vector's component on the known-payload column is |δ| = {delta:.2g} "
            f"(≤ {DELTA_TOL:.0e})"
        )


def tls_from_factor(r: np.ndarray) -> TLSResult:
    """Total least squares from the R factor of A (its last column is the δ column).

    Raises
    ------
    IdentificationError
        The δ component vanishes: no TLS solution with a finite scale exists.
    """
    k = r.shape[1]
    _, s, vt = np.linalg.svd(r, full_matrices=False)
    v = vt[-1]
    delta = float(v[-1])
    if not np.isfinite(delta) or abs(delta) <= DELTA_TOL:
        raise ScaleError(abs(delta) if np.isfinite(delta) else float("nan"))
    gap = float(s[-2] / s[-1]) if k > 1 and s[-1] > 0.0 else np.inf
    return TLSResult(
        x=v / delta,
        vector=v,
        singular_values=s,
        delta_component=abs(delta),
        gap=gap,
        r_theta=r[: k - 1, : k - 1],
    )


def tls_scores(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Per-row terms ψ_k of the TLS estimating equation, at the solution ``x`` (δ = 1).

    With θ = x[:-1] the TLS estimate minimises f(θ) = ‖A [θ; 1]‖² / (1 + θᵀθ); ∇f = 0 reads
    Σ_k ψ_k = 0 with ψ_k = a_k,θ·r_k − r_k²·θ/(1 + θᵀθ), r_k = a_k·x. Returns (rows, k−1).
    """
    theta = x[:-1]
    res = a @ x
    return a[:, :-1] * res[:, None] - np.outer(res**2, theta) / (1.0 + theta @ theta)


def tls_covariance(tls: TLSResult, meat: np.ndarray, n_clusters: int, n_rows: int) -> np.ndarray:
    """First-order (sandwich) covariance of θ = x[:-1] of a TLS solution.

    θ̂ solves ψ(θ) = Σ_k ψ_k(θ) = 0 (see :func:`tls_scores`). Linearising about the limit,
    θ̂ − θ ≈ −J⁻¹ ψ with J = ∂ψ/∂θ = A_θᵀA_θ − s_k²·I (the gradient of s_k² vanishes at the
    solution), so Cov(θ̂) = J⁻¹ Cov(ψ) J⁻¹. Cov(ψ) is estimated from ``meat`` = Σ_c Ψ_c Ψ_cᵀ over
    clusters c of rows whose errors may be correlated (Ψ_c the sum of ψ_k over the cluster;
    clusters independent of each other), which stays valid when equation errors are correlated
    within a cluster and differ between rows. The usual small-sample factor
    C/(C − 1)·(N − 1)/(N − p) is applied. J⁻¹ comes from the SVD of R_θ:
    J = V (S² − s_k²) Vᵀ, never from inverting a formed AᵀA.

    Parameters
    ----------
    tls
        The TLS solution (its ``r_theta`` and smallest singular value).
    meat
        Σ_c Ψ_c Ψ_cᵀ, (k−1, k−1).
    n_clusters
        Number of clusters C summed in ``meat``.
    n_rows
        Number of rows N of A.
    """
    _, s, vt = np.linalg.svd(tls.r_theta)
    d = s**2 - tls.lam
    if np.any(d <= 0.0):
        raise IdentificationError("IDIM-WTLS: the solution is not unique (no covariance)")
    j_inv = (vt.T / d) @ vt
    p = meat.shape[0]
    if n_clusters < 2 or n_rows <= p:
        return np.full((p, p), np.inf)
    correction = n_clusters / (n_clusters - 1) * (n_rows - 1) / (n_rows - p)
    cov = j_inv @ meat @ j_inv * correction
    return np.asarray(0.5 * (cov + cov.T))


def cluster_sums(x: np.ndarray, labels: np.ndarray, n_clusters: int) -> np.ndarray:
    """Sums of the rows of ``x`` (rows, ...) by cluster label (0..n_clusters−1)."""
    out = np.zeros((n_clusters, *x.shape[1:]))
    np.add.at(out, labels, x)
    return out
