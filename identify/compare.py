"""Alternative drive-gain estimators, for the validation study (benchmarks/validate.py).

Every function takes the same two designs as :func:`drivegain.identify.gains.identify_gains`
(run a unloaded, run b with a payload of known mass, :class:`~drivegain.identify.design.Design`)
and returns a :class:`GainEstimate`, so the estimators can be compared on exactly the same data:

- :func:`wtls_gains`: IDIM-WTLS as in the paper (our procedure; a thin wrapper);
- :func:`tls_gains`: plain total least squares of the same total matrix, no row weights, α = 1;
  with :func:`diagonal_design` it ignores the coupled current matrix of the wrist (eq. 21), which
  is what an implementation without the coupling does;
- :func:`per_joint_gains`: each joint's gain from its own equations (Gautier & Briot, IROS 2011:
  the current reference of joint j is linear in χ/g_j, χ_uL/g_j and 1/g_j, the latter multiplying
  the known-mass column), by ordinary least squares per joint;
- :func:`global_ls_gains`: one weighted least-squares problem for all unknowns (χ, g, χ_uL) with
  the known-mass column moved to the right-hand side.

Rows of every run and joint are ``D_j = [W_base | W_payload | V_j]`` (see ``Design.block``);
each estimator applies a column transform ``T`` to them, so the unknowns and the right-hand
side are combinations of a design's columns.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from drivegain.config.payload import PAYLOAD_PARAMS, Payload
from drivegain.errors import IdentificationError, InputError
from drivegain.identify.casenoise import CaseNoise
from drivegain.identify.design import Design
from drivegain.identify.estimate import ls_from_factor, r_factor, tls_from_factor
from drivegain.identify.gains import (
    DEFAULT_ALPHA_GRID,
    Estimator,
    GainIdentification,
    estimate_gains,
    identify_gains,
)
from drivegain.identify.weighting import EXACT_TOL, SIGMA_MAX_ITER, SIGMA_TOL, floor_sigma

#: Per-joint LS: a column whose distance to the span of the previously kept columns is below
#: this fraction of its norm (after unit scaling) is left out as not identifiable from this
#: joint's equations alone.
JOINT_RANK_TOL = 1e-8


@dataclass(frozen=True)
class GainEstimate:
    """Drive gains from one estimator.

    Attributes
    ----------
    method
        Short name of the estimator.
    gains
        Drive gains, N·m/A, (n,).
    std
        One standard deviation per gain as the method reports it, N·m/A, or None when the
        method reports none.
    coupled
        Whether the estimator's model has the coupled current matrix of eq. (21).
    details
        Diagnostics (α, iterations, ...).
    gain_cov
        Covariance of the gains, (N·m/A)², (n, n), when the method gives one (carried into the
        Case 2 payload fits, :func:`~drivegain.identify.cases.fit_case`).
    noise
        The method's error model, when it has one (:mod:`~drivegain.identify.casenoise`; for
        the Case 2 payload fits' covariance).
    """

    method: str
    gains: np.ndarray
    std: np.ndarray | None
    coupled: bool
    details: dict[str, float] = field(default_factory=dict)
    gain_cov: np.ndarray | None = None
    noise: CaseNoise | None = None


def diagonal_design(d: Design) -> Design:
    """The same rows with a diagonal current matrix: joint j's torque is ``g_j v_j`` only.

    On the TX-40 this drops ``g6 v6`` from joint 5's equation, the coupling of eq. (21).
    """
    return Design(run=d.run, base_idx=d.base_idx, payload_idx=d.payload_idx, kt=np.eye(d.n))


def _known(payload: Payload, names: Sequence[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mask over :data:`PAYLOAD_PARAMS` of the known parameters and their values."""
    if names is None:
        known = payload.known_mask()
    else:
        bad = [p for p in names if p not in PAYLOAD_PARAMS]
        if bad:
            # A programming error of the caller (a Python argument, not a file or an option),
            # and tests/validation pins ValueError: kept as it is.
            raise InputError(
                f"unknown payload parameters {bad}; expected some of {PAYLOAD_PARAMS}", key="known"
            )
        known = np.array([p in names for p in PAYLOAD_PARAMS])
    if not known.any():
        raise IdentificationError(
            f"payload {payload.name!r} has no known parameter: the gains have no scale"
        )
    values = payload.values[known]
    if not np.all(np.isfinite(values)):
        raise IdentificationError(f"payload {payload.name!r}: a known parameter has no value")
    return known, values


def _check_pair(a: Design, b: Design) -> None:
    if a.loaded or not b.loaded:
        raise IdentificationError("the estimators need run a unloaded and run b loaded")
    if a.nb != b.nb or a.n != b.n:
        raise IdentificationError("runs a and b must be seen through the same base parameters")


def total_transform(
    nb: int, n: int, known: np.ndarray, chi_known: np.ndarray, alpha: float
) -> np.ndarray:
    """T with ``D_j T = [−W, αV_j, −W_uL, −W_kL χ_kL]`` (eq. 19), (nb + 10 + n, nb + n + nu + 1).

    The payload columns of an unloaded run are zero, so the same T serves both runs.
    """
    unknown = np.flatnonzero(~known)
    t = np.zeros((nb + len(PAYLOAD_PARAMS) + n, nb + n + unknown.size + 1))
    t[:nb, :nb] = -np.eye(nb)
    t[nb + 10 :, nb : nb + n] = alpha * np.eye(n)
    for col, p in enumerate(unknown):
        t[nb + p, nb + n + col] = -1.0
    t[nb + np.flatnonzero(known), -1] = -chi_known
    return t


def wtls_gains(a: Design, b: Design, payload: Payload, apriori: np.ndarray) -> GainEstimate:
    """IDIM-WTLS of the paper (row weights 1/σ_j iterated, α by the error norm): ours.

    Parameters
    ----------
    a, b
        Designs of run a (unloaded) and run b (with ``payload``).
    payload
        Payload of run b; its ``known`` parameters set the scale.
    apriori
        A priori gains, N·m/A (first σ_j only).

    Returns
    -------
    GainEstimate
        Gains (N·m/A) with the sandwich standard deviations of
        :func:`~drivegain.identify.gains.identify_gains`; ``details``: α, singular value
        gap, σ iterations, covariance block length (samples).
    """
    res = identify_gains(a, b, payload, np.asarray(apriori, dtype=float))
    assert res.fit is not None  # the paper's estimator always has its WTLS fit
    return _estimate(
        "IDIM-WTLS",
        a,
        res,
        {
            "alpha": res.fit.alpha,
            # 1.0 when α ended at an end of the searched grid (the criterion chose nothing).
            "alpha_at_edge": float(
                res.fit.alpha <= min(DEFAULT_ALPHA_GRID) or res.fit.alpha >= max(DEFAULT_ALPHA_GRID)
            ),
            "gap": res.fit.tls.gap,
            "sigma_iterations": float(res.fit.iterations),
            "block": float(res.block),
        },
    )


def ours_gains(a: Design, b: Design, payload: Payload, apriori: np.ndarray) -> GainEstimate:
    """The default estimator: maximum likelihood in current units (:mod:`~drivegain.identify.ml`).

    Arguments as :func:`wtls_gains` (``apriori`` is unused: the search starts from a least
    squares). Returns the gains (N·m/A) with standard deviations and covariance from the
    errors' autocovariance (:mod:`~drivegain.identify.autocov`); ``details``: its longest lag
    (samples), search rounds, and the errors-in-variables test's statistic and p-value.
    """
    res = estimate_gains(a, b, payload, np.asarray(apriori, dtype=float), estimator=Estimator.ML)
    assert res.ml is not None and res.eiv is not None  # the ML branch always sets both
    return _estimate(
        "ML",
        a,
        res,
        {
            "lag": float(res.ml.lag),
            "rounds": float(res.ml.iterations),
            "eiv_statistic": res.eiv.statistic,
            "eiv_p": res.eiv.p_value,
        },
    )


def _estimate(
    method: str, a: Design, res: GainIdentification, details: dict[str, float]
) -> GainEstimate:
    """The :class:`GainEstimate` of an estimator of :mod:`drivegain.identify.gains`: its gains,
    standard deviations and the gains' block of its covariance."""
    nb, n = a.nb, a.n
    return GainEstimate(
        method=method,
        gains=res.gains,
        std=res.std,
        coupled=not np.allclose(a.kt, np.eye(n)),
        details=details,
        gain_cov=np.asarray(res.covariance[nb : nb + n, nb : nb + n]),
        noise=res.noise,
    )


def tls_gains(a: Design, b: Design, payload: Payload, *, alpha: float = 1.0) -> GainEstimate:
    """Unweighted total least squares of ``[−W, αV, −W_uL, −W_kL χ_kL] χ_tot ≈ 0``, δ = 1.

    No row weighting and a fixed column weight α: the TLS of Gautier et al. (1994) with the
    known payload mass as the scale. Reports no standard deviations.

    Parameters
    ----------
    a, b
        Designs of run a (unloaded) and run b (with ``payload``); pass
        :func:`diagonal_design` of them for the variant without the coupled current matrix.
    payload
        Payload of run b; its ``known`` parameters set the scale.
    alpha
        Weight of the current columns (dimensionless, the V columns are in A).

    Returns
    -------
    GainEstimate
        Gains, N·m/A; ``details["gap"]``: ratio of the two smallest singular values.
    """
    _check_pair(a, b)
    known, chi_known = _known(payload)
    t = total_transform(a.nb, a.n, known, chi_known, alpha)
    blocks = [d.block(j) @ t for d in (a, b) for j in range(d.n)]
    sol = tls_from_factor(r_factor(np.vstack(blocks)))
    gains = alpha * sol.x[a.nb : a.nb + a.n]
    coupled = not np.allclose(a.kt, np.eye(a.n))
    return GainEstimate(
        method="TLS", gains=gains, std=None, coupled=coupled, details={"gap": sol.gap}
    )


def _independent(a: np.ndarray, tol: float = JOINT_RANK_TOL) -> np.ndarray:
    """Indices of a maximal set of linearly independent columns of ``a`` (pivoted QR)."""
    norms = np.linalg.norm(a, axis=0)
    live = np.flatnonzero(norms > tol * max(float(norms.max(initial=0.0)), np.finfo(float).tiny))
    if live.size == 0:
        return live
    _, r, piv = scipy.linalg.qr(a[:, live] / norms[live], mode="economic", pivoting=True)
    d = np.abs(np.diag(r))
    rank = int(np.sum(d > tol * d[0]))
    return np.sort(live[piv[:rank]])


def _solve_order(kt: np.ndarray) -> list[int]:
    """Joints in an order where every other motor acting on a joint is solved before it."""
    n = kt.shape[0]
    order: list[int] = []
    pending = list(range(n))
    while pending:
        ready = [j for j in pending if all(m in order for m in np.flatnonzero(kt[j]) if m != j)]
        if not ready:
            raise IdentificationError("the current coupling has a cycle: no per-joint order")
        order += ready
        pending = [j for j in pending if j not in ready]
    return order


def per_joint_gains(
    a: Design, b: Design, payload: Payload, *, known: Sequence[str] | None = None
) -> GainEstimate:
    """Each joint's gain from its own equations, by OLS (the approach before the paper).

    For joint j, both runs' equations are divided by g_j (Gautier & Briot, IROS 2011)::

        v_j = W_j (χ/g_j) + W_uL,j (χ_uL/g_j) + c_j (1/g_j),
        c_j = W_kL,j χ_kL − Σ_{m≠j} V_jm ĝ_m,

    with ``v_j`` the current reference of drive j. The coefficient of the known column c_j is
    1/g_j. The unknown parameters are a separate copy per joint (the scale differs), which is
    what "separately" costs: no parameter is shared between joints' equations. Coupled motors
    (drive 6 acting on joint 5 on the TX-40) enter through ``c_j`` with their gain from the
    joint solved first, so joint 6 is solved before joint 5. Columns that joint j's equations
    cannot separate are left out (pivoted QR). σ(g_j) = σ(1/g_j)·g_j² from eq. (10), without
    the uncertainty of the ĝ_m carried into ``c_j``.

    ``known``: names of the payload parameters taken as known (default: the payload's own
    ``known``). With the mass alone, the wrist joints of the TX-40 have no scale: the payload
    is fixed at the wrist centre, on the axes of joints 4-6, so its mass produces no torque
    there and only the global estimators carry the scale to them through shared parameters.

    Parameters
    ----------
    a, b
        Designs of run a (unloaded) and run b (with ``payload``).
    payload
        Payload of run b with its nominal values (kg, kg·m, kg·m²).
    known
        Names from :data:`~drivegain.config.payload.PAYLOAD_PARAMS` (``"XX"`` ... ``"M"``)
        taken as known, or None for ``payload.known``.

    Returns
    -------
    GainEstimate
        Gains and standard deviations, N·m/A; ``details["dropped_columns"]``: columns left
        out over all joints as not separable from a joint's own equations.

    Raises
    ------
    IdentificationError
        A joint's known column is zero or not separable from its other columns.
    ValueError
        ``known`` names a parameter that does not exist.
    """
    _check_pair(a, b)
    mask, chi_known = _known(payload, known)
    nb, n = a.nb, a.n
    unknown = np.flatnonzero(~mask)
    kt = a.kt
    gains = np.zeros(n)
    std = np.zeros(n)
    dropped = 0
    for j in _solve_order(kt):
        parts = []
        for d in (a, b):
            blk = d.block(j)
            w_base = blk[:, :nb]
            w_pay = blk[:, nb : nb + 10]
            v = blk[:, nb + 10 :]  # V_j: v_m · kt[j, m]
            c = w_pay[:, mask] @ chi_known
            for m in np.flatnonzero(kt[j]):
                if m != j:
                    c = c - v[:, m] * gains[m]
            parts.append(np.column_stack([w_base, w_pay[:, unknown], c, v[:, j]]))
        rows = np.vstack(parts)
        x_cols, c_col, y_col = rows[:, :-2], rows[:, -2], rows[:, -1]
        keep = _independent(x_cols)
        dropped += x_cols.shape[1] - keep.size
        a_mat = np.column_stack([x_cols[:, keep], c_col])
        names = ", ".join(p for p, k in zip(PAYLOAD_PARAMS, mask, strict=True) if k)
        if not np.any(c_col):
            raise IdentificationError(
                f"joint {j + 1}: the known payload parameters ({names}) produce no torque on "
                "this joint, so its own equations give its gain no scale"
            )
        if _independent(a_mat).size < a_mat.shape[1]:
            raise IdentificationError(
                f"joint {j + 1}: the known payload column ({names}) is not separable from the "
                "other columns of this joint's equations"
            )
        res = ls_from_factor(r_factor(np.column_stack([a_mat, y_col])), rows.shape[0])
        inv_g, inv_std = float(res.x[-1]), float(res.std[-1])
        if inv_g == 0.0:
            raise IdentificationError(f"joint {j + 1}: 1/g identified as 0")
        gains[j] = 1.0 / inv_g
        std[j] = inv_std / inv_g**2
    return GainEstimate(
        method="per-joint LS",
        gains=gains,
        std=std,
        coupled=not np.allclose(kt, np.eye(n)),
        details={"dropped_columns": float(dropped)},
    )


def _ls_transform(nb: int, n: int, known: np.ndarray, chi_known: np.ndarray) -> np.ndarray:
    """T with ``D_j T = [−W, V_j, −W_uL | W_kL χ_kL]``: unknowns (χ, g, χ_uL), then the RHS."""
    t = total_transform(nb, n, known, chi_known, 1.0)
    t[:, -1] *= -1.0
    return t


def global_ls_gains(
    a: Design, b: Design, payload: Payload, *, weighted: bool = True
) -> GainEstimate:
    """One least-squares problem for (χ, g, χ_uL) with the known-mass column on the right::

        V g − W χ − W_uL χ_uL = W_kL χ_kL      (zero right-hand side in run a's rows)

    Rows of joint j are weighted by 1/σ_j re-estimated from this fit's own residuals until they
    settle (``weighted``), as our WTLS does, so that the comparison isolates LS against TLS.
    Standard deviations by eq. (10) of the weighted system. The noisy current columns V are
    regressors here, which LS assumes exact (errors-in-variables).

    Parameters
    ----------
    a, b
        Designs of run a (unloaded) and run b (with ``payload``).
    payload
        Payload of run b; its ``known`` parameters form the right-hand side.
    weighted
        Iterate the row weights 1/σ_j (N·m⁻¹); False gives the ordinary LS.

    Returns
    -------
    GainEstimate
        Gains and standard deviations, N·m/A; ``details``: σ iterations, convergence (0/1).
    """
    _check_pair(a, b)
    known, chi_known = _known(payload)
    nb, n = a.nb, a.n
    t = _ls_transform(nb, n, known, chi_known)
    k = t.shape[1] - 1
    blocks = [(j, r_factor(d.block(j)) @ t) for d in (a, b) for j in range(n)]
    rows_joint = a.rows + b.rows
    rows_total = rows_joint * n
    y_sq = sum(float(np.sum(blk[:, -1] ** 2)) for _, blk in blocks)
    sigma = np.ones(n)
    it = 0
    converged = not weighted
    while True:
        r = r_factor(np.vstack([blk / sigma[j] for j, blk in blocks]))
        res = ls_from_factor(r, rows_total)
        if converged or it >= SIGMA_MAX_ITER:
            break
        x_aug = np.append(res.x, -1.0)
        sq = np.zeros(n)
        for j, blk in blocks:
            sq[j] += float(np.sum((blk @ x_aug) ** 2))
        if sq.sum() <= EXACT_TOL**2 * y_sq:
            converged = True  # exact data: σ_j would be round-off
            break
        new = floor_sigma(np.sqrt(sq / (rows_joint * (1.0 - k / rows_total))))
        change = float(np.max(np.abs(new / sigma - 1.0)))
        sigma = new
        it += 1
        converged = change < SIGMA_TOL
    return GainEstimate(
        method="global LS",
        gains=res.x[nb : nb + n].copy(),
        std=res.std[nb : nb + n].copy(),
        coupled=not np.allclose(a.kt, np.eye(n)),
        details={"sigma_iterations": float(it), "converged": float(converged)},
    )


def coverage(
    estimates: Sequence[np.ndarray], stds: Sequence[np.ndarray], truth: np.ndarray, k: float = 2.0
) -> np.ndarray:
    """Fraction of estimates whose ±k·σ interval holds the truth, per component.

    Parameters
    ----------
    estimates, stds
        One (n,) array per repetition: values and their reported standard deviations.
    truth
        True values, (n,).
    k
        Interval half-width in standard deviations.
    """
    e = np.asarray(estimates, dtype=float)
    s = np.asarray(stds, dtype=float)
    return np.asarray(np.mean(np.abs(e - np.asarray(truth)[None, :]) <= k * s, axis=0))


@dataclass(frozen=True)
class SeedSpread:
    """Gains identified from many noise seeds against the true ones (a simulation study).

    Attributes
    ----------
    errors
        Relative errors ĝ/g − 1, (seeds, n).
    z
        Standardised errors (ĝ − g)/σ̂, (seeds, n): about N(0, 1) when σ̂ is honest.
    """

    errors: np.ndarray
    z: np.ndarray

    @classmethod
    def of(
        cls, gains: Sequence[np.ndarray], stds: Sequence[np.ndarray], truth: np.ndarray
    ) -> SeedSpread:
        """From the gains (N·m/A) and their standard deviations, one (n,) array per seed, and
        the true gains, (n,)."""
        g = np.asarray(gains, dtype=float)
        return cls(errors=g / truth - 1.0, z=(g - truth) / np.asarray(stds, dtype=float))

    @property
    def inside(self) -> np.ndarray:
        """Whether ±2σ̂ holds the truth, (seeds, n)."""
        return np.asarray(np.abs(self.z) < 2.0)

    def describe(self) -> list[str]:
        """Two lines: the largest error and the coverage of the truth by ±2σ̂; the mean and
        spread of z, per joint."""
        inside = self.inside
        return [
            f"max |gain error| {100 * np.abs(self.errors).max():.3f} %; truth within 2σ "
            f"{inside.mean():.1%} of {inside.size} (per joint "
            + ", ".join(f"{v:.0%}" for v in inside.mean(axis=0))
            + ")",
            "z = (ĝ−g)/σ̂: mean per joint "
            + ", ".join(f"{v:+.2f}" for v in self.z.mean(axis=0))
            + "; standard deviation per joint "
            + ", ".join(f"{v:.2f}" for v in self.z.std(axis=0)),
        ]
