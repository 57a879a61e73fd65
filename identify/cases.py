"""IDIM-WLS with known gains: Case 1 (a priori gains), Case 2 (identified gains), validation.

The base parameters and every loaded run's 10 payload parameters are solved together by
weighted least squares (Gautier & Briot 2012, §4), rows of joint j weighted by 1/σ_j from an OLS
of joint j's equations alone (Gautier 1997). Standard deviations: a HAC sandwich
(:mod:`drivegain.identify.hac`: the decimated equation errors are correlated in time) plus,
when the gains come with a covariance, their uncertainty carried through the fit (the gains
scale the torques V·g the fit explains); eq. (8)-(11)'s white-noise values stay in ``wls``.
Also the fit quality measures every case reports (R² and relative residual norm per joint).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from drivegain.config.payload import PAYLOAD_PARAMS
from drivegain.errors import UsageError
from drivegain.identify.casenoise import CaseNoise, gain_scores, model_sums
from drivegain.identify.design import (
    Design,
    joint_residual_sq,
    ls_transform,
    run_phases,
    same_phases,
    stacked_factor,
)
from drivegain.identify.estimate import LSResult, cluster_sums, ls_from_factor
from drivegain.identify.hac import (
    LongRunSum,
    bartlett_lag,
    gathered,
    matched_root,
    sandwich,
    with_repeats,
)
from drivegain.identify.leaveout import misfit_drives, near_reversals, without_rows
from drivegain.identify.predict import prediction_quality, predictions
from drivegain.identify.weighting import joint_sigma


@dataclass(frozen=True)
class PayloadEstimate:
    """Identified inertial parameters of one payload (order XX XY XZ YY YZ ZZ MX MY MZ M)."""

    name: str
    values: np.ndarray
    std: np.ndarray
    nominal: np.ndarray
    known: tuple[str, ...]


class CaseCovariance(StrEnum):
    """How a case's standard deviations were computed (report.json's ``covariance``)."""

    NEWEY_WEST = "HAC (Newey-West, Bartlett kernel)"
    NEWEY_WEST_GAINS = "HAC (Newey-West, Bartlett kernel) with the gains' covariance"
    ERROR_MODEL = (
        "the maximum-likelihood gains' error model (its whitened errors' autocovariance), "
        "with the gains' covariance and their correlation with this fit"
    )
    NEWEY_WEST_KEPT = (
        "HAC (Newey-West, Bartlett kernel) with the gains' covariance and their lagged "
        "correlation with this fit's residuals, on the entries away from the reversals the "
        "gains' error model finds misfit"
    )


@dataclass(frozen=True)
class CaseResult:
    """One IDIM-WLS identification with fixed gains (a column of Tables 2, 4 or 5).

    Attributes
    ----------
    name
        ``case1``, ``case2``, ``given``.
    gains
        Drive gains used, N·m/A.
    base_names, base, base_std
        Base parameters, their values and standard deviations (HAC, with the gains'
        uncertainty when given; eq. (10)'s are in ``wls.std``).
    payloads
        Identified payloads (one per loaded run).
    residual_norm
        ‖ρ‖ = ‖Y − W χ̂‖, N·m, unweighted.
    relative_error
        ‖ρ‖ / ‖Y‖.
    sigma_rho
        ‖ρ‖ / √(r − b), N·m (Table 4).
    sigma_joint
        σ̂_j used to weight the rows, N·m.
    r2, joint_relative
        Per joint: R² of measured against computed torque, and ‖ρ_j‖/‖Y_j‖.
    rows
        Equations r the fit used (every entry less ``left_out``).
    wls
        The weighted solution with its statistics (eq. 8-11, white noise assumed).
    lag
        Newey-West lag of the HAC standard deviations, or with the gains' error model the
        longest lag of its autocovariance, samples.
    covariance
        How the standard deviations were computed.
    left_out
        Entries (sample and joint) the fit left out near reversals of the drives whose
        entries there the gains' error model finds misfit
        (:func:`~drivegain.identify.leaveout.misfit_drives`); the error norms and R² still
        count every entry.
    """

    name: str
    gains: np.ndarray
    base_names: list[str]
    base: np.ndarray
    base_std: np.ndarray
    payloads: list[PayloadEstimate]
    residual_norm: float
    relative_error: float
    sigma_rho: float
    sigma_joint: np.ndarray
    r2: np.ndarray
    joint_relative: np.ndarray
    rows: int
    wls: LSResult
    lag: int = 0
    covariance: CaseCovariance = CaseCovariance.NEWEY_WEST
    left_out: int = 0

    def coefficients(self) -> tuple[np.ndarray, list[np.ndarray]]:
        return self.base, [p.values for p in self.payloads]


def _payload_slots(designs: Sequence[Design]) -> list[int | None]:
    slots: list[int | None] = []
    k = 0
    for d in designs:
        if d.loaded:
            slots.append(k)
            k += 1
        else:
            slots.append(None)
    return slots


def fit_case(
    name: str,
    designs: Sequence[Design],
    gains: np.ndarray,
    base_names: Sequence[str],
    factors: Sequence[np.ndarray] | None = None,
    gain_cov: np.ndarray | None = None,
    covariance: bool = True,
    noise: CaseNoise | None = None,
    leave_out_misfit: bool = True,
) -> CaseResult:
    """IDIM-WLS of the base parameters and every loaded run's 10 payload parameters.

    Rows of joint j are weighted by 1/σ_j from an OLS of joint j's equations alone
    (Gautier 1997); standard deviations by :func:`case_covariance`.

    Where the gains' error model finds a drive's entries near its reversals misfit
    (:func:`~drivegain.identify.leaveout.misfit_drives`: it sticks there, or its Coulomb sign
    is uncertain), the entries near those reversals
    (:func:`~drivegain.identify.leaveout.near_reversals`) are left out of the fit and its
    standard deviations, which are then Newey-West's with the gains' covariance and their
    correlation with this fit's residuals (:func:`~.casenoise.gain_scores`): that torque is a
    misfit, not noise, and the fit would borrow the payload's inertias to explain it
    (docs/model.md, "Case 2 without the misfit reversals"). The error norms and R² count
    every entry.

    Parameters
    ----------
    name
        Name of the case.
    designs
        The runs fitted together.
    gains
        Drive gains, N·m/A.
    base_names
        Names of the base parameters.
    factors
        Per run, the R factors of every joint's rows (computed when omitted).
    gain_cov
        Covariance of ``gains`` ((N·m/A)², (n, n)), carried into the standard deviations;
        None for gains taken as exact (a priori or given without σ).
    covariance
        False skips the HAC standard deviations (NaN, lag 0): a fit whose estimate alone is
        used (the cross-validation's) is spared two passes over its rows.
    noise
        The error model of the estimator that gave ``gains`` (:mod:`.casenoise`), for
        standard deviations under it, with the gains' correlation with this fit's noise;
        None: Newey-West, the gains taken as independent.
    leave_out_misfit
        False fits every entry whatever the error model says.
    """
    if noise is not None and gain_cov is None:
        # checked here too: leaving entries out drops the model before case_covariance sees it
        raise UsageError("a noise model comes with the gains' covariance (gain_cov)")
    gains = np.asarray(gains, dtype=float)
    if factors is None:
        factors = [d.factors() for d in designs]
    every, every_factors = list(designs), list(factors)
    scores = None
    if noise is not None and leave_out_misfit:
        drives = misfit_drives(noise)
        drops = [near_reversals(d, drives=drives) for d in designs]
        if any(x.any() for x in drops):
            designs = [without_rows(d, x) for d, x in zip(designs, drops, strict=True)]
            factors = [d.factors() for d in designs]
            if covariance:
                scores = [gain_scores(noise, d) for d in designs]
            noise = None
    slots = _payload_slots(designs)
    n_slots = sum(s is not None for s in slots)
    transforms = [ls_transform(d, s, n_slots, gains) for d, s in zip(designs, slots, strict=True)]
    names = list(base_names)
    for d, s in zip(designs, slots, strict=True):
        if s is not None and d.run.payload is not None:
            names += [f"{p}_{d.run.payload.name}" for p in PAYLOAD_PARAMS]
    sigma = joint_sigma(designs, factors, transforms)
    rows = sum(d.entries(j) for d in designs for j in range(designs[0].n))
    r = stacked_factor(factors, transforms, 1.0 / sigma)
    res = ls_from_factor(r, rows, names)
    x_aug = np.append(res.x, -1.0)
    res_sq = joint_residual_sq(every_factors, transforms, x_aug)
    y_sq = joint_residual_sq(every_factors, transforms, np.append(np.zeros(res.x.size), 1.0))
    nb = designs[0].nb
    if covariance:
        cov, lag = case_covariance(
            designs, transforms, sigma, res.x, gain_cov, factors, noise=noise, gain_scores=scores
        )
        std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    else:
        std, lag = np.full(res.x.size, np.nan), 0
    chi = res.x[:nb]
    payloads = []
    for d, s in zip(designs, slots, strict=True):
        if s is None or d.run.payload is None:
            continue
        sl = slice(nb + 10 * s, nb + 10 * (s + 1))
        payloads.append(
            PayloadEstimate(
                name=d.run.payload.name,
                values=res.x[sl],
                std=std[sl],
                nominal=d.run.payload.values.copy(),
                known=d.run.payload.known,
            )
        )
    r2, joint_rel = _joint_quality(every, gains, chi, [p.values for p in payloads])
    rho = float(np.sqrt(res_sq.sum()))
    every_rows = sum(d.entries(j) for d in every for j in range(every[0].n))
    left_out = every_rows - rows  # entries the designs' own row weights drop are in neither
    how = CaseCovariance.NEWEY_WEST
    if left_out:
        how = CaseCovariance.NEWEY_WEST_KEPT
    elif noise is not None:
        how = CaseCovariance.ERROR_MODEL
    elif gain_cov is not None:
        how = CaseCovariance.NEWEY_WEST_GAINS
    return CaseResult(
        name=name,
        gains=gains,
        base_names=list(base_names),
        base=chi,
        base_std=std[:nb],
        payloads=payloads,
        residual_norm=rho,
        relative_error=rho / float(np.sqrt(y_sq.sum())),
        sigma_rho=rho / np.sqrt(max(every_rows - res.x.size, 1)),
        sigma_joint=sigma,
        r2=r2,
        joint_relative=joint_rel,
        rows=rows,
        wls=res,
        lag=lag,
        covariance=how,
        left_out=left_out,
    )


def case_covariance(
    designs: Sequence[Design],
    transforms: Sequence[np.ndarray],
    sigma: np.ndarray,
    x: np.ndarray,
    gain_cov: np.ndarray | None = None,
    factors: Sequence[np.ndarray] | None = None,
    *,
    noise: CaseNoise | None = None,
    gain_scores: Sequence[np.ndarray | None] | None = None,
) -> tuple[np.ndarray, int]:
    """HAC covariance of an IDIM-WLS solution, plus the gains' share when they are uncertain.

    With A the weighted columns and c = V·g/σ_j the weighted torques, x̂ = H⁻¹Aᵀc (H = AᵀA).
    Per-sample scores ψ_k = Σ_j a_jk (a_jkᵀx̂ − c_jk) give the Newey-West covariance
    (:mod:`~drivegain.identify.hac`), lag from the weighted residuals, each σ raised where the
    scores summed by phase of a periodic excitation say so
    (:func:`~drivegain.identify.hac.with_repeats`); the gains enter c
    linearly, so ∂x̂/∂g = H⁻¹Aᵀ ∂c/∂g and their covariance adds J_g Cov(g) J_gᵀ. With
    ``gain_scores`` (each sample's share φ_k of the gains' error) their correlation with this
    fit is the Newey-West sum of the lagged products ψ_k φ_k'ᵀ, φ mapped onto the gains' own
    covariance (:func:`~.hac.matched_root`); without, the gains are taken as independent.

    Parameters
    ----------
    designs, transforms, sigma, x, gain_cov
        The runs, their column transforms, σ̂_j (N·m), the solution and the gains'
        covariance ((N·m/A)², (n, n), or None) of :func:`fit_case`.
    factors
        Per run, the R factors of every joint's rows (computed when omitted).
    noise
        The error model of the estimator that gave the gains (:mod:`.casenoise`): the meat is
        then that model's rather than Newey-West's, and the gains' covariance with this fit's
        noise is added (with ``gain_cov``, which it needs).
    gain_scores
        Per design, φ_k (N·m/A, (N, n)) of :func:`~drivegain.identify.casenoise.gain_scores`,
        or None for a run the gains did not use; read with ``gain_cov`` and without ``noise``.

    Returns
    -------
    covariance, lag
        (p, p) in the order of ``x``; the lag in samples (the model's with ``noise``).
    """
    if noise is not None and gain_cov is None:
        raise UsageError("a noise model comes with the gains' covariance (gain_cov)")
    if gain_scores is not None and (gain_cov is None or noise is not None):
        raise UsageError("the gains' scores come with their covariance and without a noise model")
    p = x.size
    n = designs[0].n
    if gain_scores is not None:
        got = [None if f is None else np.shape(f) for f in gain_scores]
        want = [
            None if f is None else (d.rows, n) for d, f in zip(designs, gain_scores, strict=False)
        ]
        if len(got) != len(designs) or got != want:
            raise UsageError(f"the gains' scores must be (rows, {n}) per design, got {got}")
    if factors is None:
        factors = [d.factors() for d in designs]
    x_aug = np.append(x, -1.0)
    bread = np.zeros((p, p))
    cross = np.zeros((p, n))
    # H and Aᵀ ∂c/∂g are Grams of the columns: from the R factors (RᵀR = D_jᵀD_j), with no
    # pass over the rows. ∂c_j/∂g_m = kt[j, m] v_m / σ_j is D_j's current column m over σ_j.
    for d, f, t in zip(designs, factors, transforms, strict=True):
        for j in range(n):
            a = f[j] @ t[:, :p] / sigma[j]
            bread += a.T @ a
            cross += a.T @ (f[j][:, d.nb + 10 :] / sigma[j])
    # The weighted residuals e_kj = D_j,k T x̂_aug / σ_j of every sample, whose autocorrelation
    # gives the lag; then the scores ψ_k = (Σ_j e_kj D_j,k / σ_j) T[:, :p] in row blocks
    # (no D_j is built) and their long-run sum with that lag.
    resid = [d.dot(t @ x_aug) / sigma[None, :] for d, t in zip(designs, transforms, strict=True)]
    lag = bartlett_lag(resid)
    # with the gains' scores one sum of [ψ_k, φ_k]: its ψ block is the fit's meat
    width = p if gain_scores is None else p + n
    meat = LongRunSum(width, lag)
    by_phase: list[np.ndarray | None] = []
    for i, (d, t, e) in enumerate(zip(designs, transforms, resid, strict=True)):
        w = e / sigma[None, :]
        phases = run_phases(d)
        folded = None if phases is None else np.zeros((phases[1], p))
        phi = None if gain_scores is None else gain_scores[i]
        for sl in _row_blocks(d.rows):
            psi = d.subset(sl).tdot(w[sl]) @ t[:, :p]
            if noise is None and width == p:
                meat.add(psi)
            elif noise is None:
                block = np.zeros((psi.shape[0], width))
                block[:, :p] = psi
                if phi is not None:
                    block[:, p:] = phi[sl]
                meat.add(block)
            if folded is not None and phases is not None:
                folded += cluster_sums(psi, phases[0][sl], phases[1])
        meat.end_run()
        by_phase.append(folded)
    rows = sum(d.entries(j) for d in designs for j in range(n))
    h_inv = np.linalg.pinv(bread, hermitian=True)
    s_uv = None
    if gain_scores is not None and gain_cov is not None:
        both_meat = meat.meat()
        cov = sandwich(bread, both_meat[:p, :p], rows, p)
        # Σ Uᵀγ V is −Σ ψ φᵀ here (ψ_k ≈ −a_k ε_k); φ mapped by T, T S_φφ Tᵀ = Cov(g), keeps
        # the whole a congruence of Newey-West's (positive semidefinite; docs/model.md)
        to_gains = matched_root(np.asarray(gain_cov, float), both_meat[p:, p:])
        s_uv = -np.sqrt(rows / (rows - p)) * both_meat[:p, p:] @ to_gains.T
    elif noise is None:
        cov = sandwich(bread, meat.meat(), rows, p)
    else:
        blocks = [_row_blocks(d.rows) for d in designs]
        s_uu, s_uv, _ = model_sums(designs, transforms, sigma, p, noise, blocks)
        cov = h_inv @ s_uu @ h_inv
        cov = 0.5 * (cov + cov.T)
    # errors that repeat every period of the excitation, as for the ML gains
    summed = gathered(by_phase, same_phases(designs))
    raised = None
    if summed is not None:
        cov, raised = with_repeats(cov, bread, summed, lag, rows)
    if gain_cov is not None:
        j_g = h_inv @ cross
        cov = cov + j_g @ np.asarray(gain_cov, float) @ j_g.T
        if s_uv is not None:
            # Cov(fit's error, gains' error) = H⁻¹ Σ Uᵀγ V, carried through J_g
            both = h_inv @ s_uv @ j_g.T
            if gain_scores is not None and raised is not None:
                both = raised[:, None] * both  # the fit's error as the repeats raised it
            cov = cov + both + both.T
    return cov, (lag if noise is None else noise.lag)


#: Samples per row block of :func:`case_covariance`'s scores (bounds the memory of long runs).
ROW_BLOCK = 2048


def _row_blocks(samples: int) -> list[slice]:
    return [slice(k, min(k + ROW_BLOCK, samples)) for k in range(0, samples, ROW_BLOCK)]


def _joint_quality(
    designs: Sequence[Design], gains: np.ndarray, chi: np.ndarray, payloads: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """R² and relative residual norm per joint of a fit on ``designs``."""
    quality = prediction_quality(predictions(designs, gains, chi, payloads))
    return quality.r2, quality.joint_relative
