"""The paper's whole procedure on prepared runs (Gautier & Briot 2012, §3-4).

1. Drive gains by IDIM-WTLS from run a (unloaded) and run b (known payload): the total matrix
   ``[−W_a, αV_a, 0, 0; −W_b, αV_b, −W_uL, −W_kL·χ_kL]`` with rows weighted by 1/σ_j, its
   smallest right singular vector scaled so that δ = 1; α chosen on a grid by the relative error
   norm; σ_j re-estimated from the WTLS residuals until they settle (σ_j from OLS with wrong a
   priori gains spoils the coupled joints 5-6, docs/model.md).
2. Case 1 (a priori gains) and Case 2 (identified gains): IDIM-WLS of the base parameters and
   the 10 payload parameters from both runs, standard deviations by eq. (8)-(11).
3. Validation: a second payload, identified from a third run with the gains of both cases
   (Table 5).
4. Quality: error norms (Table 4), per-joint R², a held-out cross-validation, both coupled-wrist
   friction forms, physical plausibility of friction and rotor inertias.

Two things go beyond the paper, both found necessary in simulation for honest results:

- the V columns are weighted by α·c_m, not one α: c_m equalises the current noise of the drives
  as it appears in the weighted rows (:func:`drive_noise_weights`). With one α the solution
  is biased by several standard deviations on two 60 s runs, because drives with small gains
  carry more noise in current units and TLS assumes isotropic noise;
- the gains' standard deviations come from a first-order (sandwich) covariance of the TLS
  solution whose scores are summed over clusters of possibly correlated samples, including
  the same phase of a periodic excitation in every period (:func:`wtls_covariance`): encoder
  quantisation repeats exactly from one period to the next.

Rows of one run and one joint are reduced once to a triangular factor; every estimator below
works on stacks of those small factors with row weights and column transforms
(:mod:`drivegain.identify.estimate`), so the α grid and the σ iteration cost almost nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from drivegain.config.payload import PAYLOAD_PARAMS, Payload
from drivegain.config.robot import Robot, WristFriction
from drivegain.dynamics.base import BaseParameters
from drivegain.errors import IdentificationError
from drivegain.identify.estimate import (
    LSResult,
    TLSResult,
    cluster_sums,
    group_sigma_from_factor,
    ls_from_factor,
    r_factor,
    tls_covariance,
    tls_from_factor,
    tls_scores,
)
from drivegain.identify.prepare import PreparedRun, base_keys, payload_keys

#: α grid (the V columns' weight): log-spaced, refined around the best point.
DEFAULT_ALPHA_GRID = tuple(float(a) for a in np.logspace(-4, 3, 15))
#: σ_j iteration: stop when no σ_j changes by more than this fraction.
SIGMA_TOL = 1e-4
SIGMA_MAX_ITER = 30
#: Warn when the two smallest singular values of the WTLS matrix are closer than this ratio.
GAP_WARN = 1.5
#: Warn when a gain's relative standard deviation exceeds this, %.
GAIN_RSD_WARN = 5.0
#: Relative error norm below which data count as exact (noise-free simulation).
EXACT_TOL = 1e-10
#: Fraction of each run held out (its end) for cross-validation.
CV_FRACTION = 0.3

Step = Callable[[str], None]


def _no_step(_: str) -> None:
    return None


# --------------------------------------------------------------------------------------------
# Designs: one prepared run seen through one friction form's base parameters


@dataclass(frozen=True)
class Design:
    """Rows of one run: per joint j, ``D_j = [W_base | W_payload | V_j]`` (N, nb + 10 + n).

    ``W_payload`` holds the inertial columns of the payload's link (zero for an unloaded run);
    ``V_j`` is row j of the coupled current matrix (eq. 21).
    """

    run: PreparedRun
    base_idx: np.ndarray
    payload_idx: np.ndarray | None
    kt: np.ndarray

    @property
    def n(self) -> int:
        return int(self.kt.shape[0])

    @property
    def nb(self) -> int:
        return int(self.base_idx.shape[0])

    @property
    def m(self) -> int:
        return self.nb + len(PAYLOAD_PARAMS) + self.n

    @property
    def rows(self) -> int:
        return self.run.samples

    @property
    def loaded(self) -> bool:
        return self.payload_idx is not None

    def block(self, j: int) -> np.ndarray:
        """``D_j`` (N, m)."""
        w = self.run.regressor[:, j, :]
        out = np.zeros((self.rows, self.m))
        out[:, : self.nb] = w[:, self.base_idx]
        if self.payload_idx is not None:
            out[:, self.nb : self.nb + 10] = w[:, self.payload_idx]
        out[:, self.nb + 10 :] = self.run.current * self.kt[j][None, :]
        return out

    def factors(self) -> np.ndarray:
        """R factors of every joint's ``D_j``: (n, m, m)."""
        return np.stack([r_factor(self.block(j)) for j in range(self.n)])

    def torque(self, gains: np.ndarray) -> np.ndarray:
        """Joint torques V·g (N·m) the current references stand for with ``gains``, (N, n)."""
        return self.run.current @ (self.kt * np.asarray(gains)[None, :]).T

    def model_torque(self, chi: np.ndarray, chi_payload: np.ndarray | None) -> np.ndarray:
        """Joint torques W·χ + W_L·χ_L of the model (N·m), (N, n)."""
        coef = np.zeros(self.run.regressor.shape[2])
        np.add.at(coef, self.base_idx, chi)
        if self.payload_idx is not None and chi_payload is not None:
            np.add.at(coef, self.payload_idx, chi_payload)
        return np.asarray(self.run.regressor @ coef)

    def subset(self, sl: slice) -> Design:
        return Design(self.run.rows(sl), self.base_idx, self.payload_idx, self.kt)


def coupling_factor(robot: Robot) -> np.ndarray:
    """kt with ``V[:, j, :] = v * kt[j]`` (eq. 21): 1 on the diagonal and at coupled motors."""
    k = robot.transmission()
    return np.asarray(k.T / np.diag(k)[None, :])


def make_design(run: PreparedRun, bp: BaseParameters, form: WristFriction, robot: Robot) -> Design:
    """The design of ``run`` for the base parameters ``bp`` of friction form ``form``."""
    base_idx = run.column_index(base_keys(bp, form))
    payload_idx = None
    if run.payload is not None:
        payload_idx = run.column_index(payload_keys(robot, run.payload.link))
    return Design(run=run, base_idx=base_idx, payload_idx=payload_idx, kt=coupling_factor(robot))


# --------------------------------------------------------------------------------------------
# Column transforms: the unknowns of each problem as combinations of a design's columns


def _ls_transform(d: Design, slot: int | None, n_slots: int, gains: np.ndarray) -> np.ndarray:
    """T with ``D T = [W_base | payload of slot | V g]`` for IDIM-(W)LS with known gains."""
    nb, m = d.nb, d.m
    k = nb + 10 * n_slots
    t = np.zeros((m, k + 1))
    t[:nb, :nb] = np.eye(nb)
    if slot is not None:
        t[nb : nb + 10, nb + 10 * slot : nb + 10 * (slot + 1)] = np.eye(10)
    t[nb + 10 :, k] = gains
    return t


def _tls_transform(
    d: Design, known: np.ndarray, chi_known: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """T with ``D T = [−W, V·diag(w), −W_uL, −W_kL χ_kL]`` (eq. 19 with per-drive column
    weights w = α·c, see :func:`drive_noise_weights`); the loaded part only if loaded."""
    nb, n, m = d.nb, d.n, d.m
    unknown = np.flatnonzero(~known)
    nu = unknown.size
    t = np.zeros((m, nb + n + nu + 1))
    t[:nb, :nb] = -np.eye(nb)
    t[nb + 10 :, nb : nb + n] = np.diag(np.broadcast_to(weights, (n,)))
    if d.loaded:
        for col, p in enumerate(unknown):
            t[nb + p, nb + n + col] = -1.0
        t[nb + np.flatnonzero(known), -1] = -chi_known
    return t


def drive_noise_weights(kt: np.ndarray, gains: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Relative weights c_m of the V columns that give every drive's column the same noise.

    The equation error of joint j is current noise through the gains:
    σ_j² = Σ_m kt[j,m]²·g_m²·σ_v,m² (eq. 21), which gives the current noise σ_v,m of each drive
    (non-negative least squares; for a robot without coupling σ_v,j = σ_j/|g_j|). In rows weighted
    by 1/σ_j, column m of V then carries noise of variance q_m = mean_j(kt[j,m]²σ_v,m²/σ_j²);
    scaling it by c_m ∝ 1/√q_m (geometric mean 1, so α keeps the paper's meaning) makes the
    noise of the V block isotropic, as total least squares assumes. With a single α for all
    columns (the paper) the solution is biased by about (noise/signal)²·r, which soon exceeds
    its standard deviation: drives with small gains carry more noise in current units.
    """
    from scipy.optimize import nnls

    m_mat = (kt**2) * (np.asarray(gains, float) ** 2)[None, :]
    var_v, _ = nnls(m_mat, np.asarray(sigma, float) ** 2)
    top = float(var_v.max()) if var_v.size else 0.0
    var_v = np.maximum(var_v, 1e-6 * top if top > 0 else 1.0)
    present = kt != 0.0
    q = np.array(
        [
            np.mean((kt[present[:, c], c] ** 2) * var_v[c] / sigma[present[:, c]] ** 2)
            for c in range(kt.shape[1])
        ]
    )
    c = 1.0 / np.sqrt(q)
    return np.asarray(c / np.exp(np.mean(np.log(c))))


def _stack(
    factors: Sequence[np.ndarray], transforms: Sequence[np.ndarray], weights: np.ndarray
) -> np.ndarray:
    """R factor of the stacked, row-weighted, column-transformed rows of several runs."""
    blocks = [
        weights[j] * (f[j] @ t)
        for f, t in zip(factors, transforms, strict=True)
        for j in range(f.shape[0])
    ]
    return r_factor(np.vstack(blocks))


def _joint_residual_sq(
    factors: Sequence[np.ndarray], transforms: Sequence[np.ndarray], x_aug: np.ndarray
) -> np.ndarray:
    """Σ over runs of ‖D_j T x‖² per joint (unweighted equation errors, N·m²)."""
    n = factors[0].shape[0]
    out = np.zeros(n)
    for f, t in zip(factors, transforms, strict=True):
        tx = t @ x_aug
        out += np.array([float(np.sum((f[j] @ tx) ** 2)) for j in range(n)])
    return out


# --------------------------------------------------------------------------------------------
# Per-joint σ (Gautier 1997): OLS of each joint's equations alone


def joint_sigma(
    designs: Sequence[Design], factors: Sequence[np.ndarray], transforms: Sequence[np.ndarray]
) -> np.ndarray:
    """σ̂_j (N·m) of an OLS fit of joint j's equations alone, for every joint."""
    n = designs[0].n
    sigma = np.empty(n)
    for j in range(n):
        rows = sum(d.rows for d in designs)
        r = r_factor(np.vstack([f[j] @ t for f, t in zip(factors, transforms, strict=True)]))
        sigma[j] = group_sigma_from_factor(r, rows).sigma
    return _floor_sigma(sigma)


def _floor_sigma(sigma: np.ndarray) -> np.ndarray:
    # Exact (noise-free) data give σ ≈ 0: keep the weights finite without changing their use.
    top = float(np.max(sigma)) if sigma.size else 0.0
    floor = max(top * 1e-9, 1e-300)
    return np.maximum(sigma, floor)


# --------------------------------------------------------------------------------------------
# IDIM-(W)LS with known gains: Case 1, Case 2, validation


@dataclass(frozen=True)
class PayloadEstimate:
    """Identified inertial parameters of one payload (order XX XY XZ YY YZ ZZ MX MY MZ M)."""

    name: str
    values: np.ndarray
    std: np.ndarray
    nominal: np.ndarray
    known: tuple[str, ...]


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
        Base parameters, their values and standard deviations (eq. 10).
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
        Equations r.
    wls
        The weighted solution with its statistics.
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
) -> CaseResult:
    """IDIM-WLS of the base parameters and every loaded run's 10 payload parameters.

    Rows of joint j are weighted by 1/σ_j from an OLS of joint j's equations alone
    (Gautier 1997); standard deviations by eq. (8)-(11) from the R factor.
    """
    gains = np.asarray(gains, dtype=float)
    if factors is None:
        factors = [d.factors() for d in designs]
    slots = _payload_slots(designs)
    n_slots = sum(s is not None for s in slots)
    transforms = [_ls_transform(d, s, n_slots, gains) for d, s in zip(designs, slots, strict=True)]
    names = list(base_names)
    for d, s in zip(designs, slots, strict=True):
        if s is not None and d.run.payload is not None:
            names += [f"{p}_{d.run.payload.name}" for p in PAYLOAD_PARAMS]
    sigma = joint_sigma(designs, factors, transforms)
    rows = sum(d.rows for d in designs) * designs[0].n
    r = _stack(factors, transforms, 1.0 / sigma)
    res = ls_from_factor(r, rows, names)
    x_aug = np.append(res.x, -1.0)
    res_sq = _joint_residual_sq(factors, transforms, x_aug)
    y_sq = _joint_residual_sq(factors, transforms, np.append(np.zeros(res.x.size), 1.0))
    nb = designs[0].nb
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
                std=res.std[sl],
                nominal=d.run.payload.values.copy(),
                known=d.run.payload.known,
            )
        )
    r2, joint_rel = _joint_quality(designs, gains, chi, [p.values for p in payloads])
    rho = float(np.sqrt(res_sq.sum()))
    return CaseResult(
        name=name,
        gains=gains,
        base_names=list(base_names),
        base=chi,
        base_std=res.std[:nb],
        payloads=payloads,
        residual_norm=rho,
        relative_error=rho / float(np.sqrt(y_sq.sum())),
        sigma_rho=rho / np.sqrt(max(rows - res.x.size, 1)),
        sigma_joint=sigma,
        r2=r2,
        joint_relative=joint_rel,
        rows=rows,
        wls=res,
    )


def _predictions(
    designs: Sequence[Design], gains: np.ndarray, chi: np.ndarray, payloads: Sequence[np.ndarray]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """(measured V·g, computed W·χ) per design, (N, n) each."""
    out = []
    k = 0
    for d in designs:
        chi_l = None
        if d.loaded:
            chi_l = payloads[k]
            k += 1
        out.append((d.torque(gains), d.model_torque(chi, chi_l)))
    return out


def _quality(pairs: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    y = np.concatenate([p[0] for p in pairs])
    yh = np.concatenate([p[1] for p in pairs])
    res = y - yh
    ss_res = np.sum(res**2, axis=0)
    ss_tot = np.sum((y - y.mean(axis=0)) ** 2, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = np.where(ss_tot > 0, 1.0 - ss_res / ss_tot, np.nan)
        rel = np.sqrt(ss_res / np.sum(y**2, axis=0))
    return r2, rel


def _joint_quality(
    designs: Sequence[Design], gains: np.ndarray, chi: np.ndarray, payloads: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    return _quality(_predictions(designs, gains, chi, payloads))


@dataclass(frozen=True)
class CrossValidation:
    """Fit on the first part of every run, prediction of the held-out end.

    Attributes
    ----------
    fraction
        Fraction of each run held out (its last samples).
    r2, joint_relative
        Per joint on the held-out samples.
    relative_error
        ‖ρ‖/‖Y‖ on the held-out samples.
    train_relative_error
        The same on the fitted samples.
    """

    fraction: float
    r2: np.ndarray
    joint_relative: np.ndarray
    relative_error: float
    train_relative_error: float


def cross_validate(
    designs: Sequence[Design],
    gains: np.ndarray,
    base_names: Sequence[str],
    fraction: float = CV_FRACTION,
) -> CrossValidation:
    """Hold out the last ``fraction`` of every run, fit IDIM-WLS on the rest, predict it."""
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction must be in (0, 1), got {fraction}")
    train, test = [], []
    for d in designs:
        split = round(d.rows * (1.0 - fraction))
        train.append(d.subset(slice(0, split)))
        test.append(d.subset(slice(split, None)))
    fit = fit_case("cv", train, gains, base_names)
    chi, payloads = fit.coefficients()
    pairs = _predictions(test, fit.gains, chi, payloads)
    r2, rel = _quality(pairs)
    y = np.concatenate([p[0] for p in pairs])
    res = y - np.concatenate([p[1] for p in pairs])
    return CrossValidation(
        fraction=fraction,
        r2=r2,
        joint_relative=rel,
        relative_error=float(np.linalg.norm(res) / np.linalg.norm(y)),
        train_relative_error=fit.relative_error,
    )


# --------------------------------------------------------------------------------------------
# IDIM-WTLS for the gains


@dataclass(frozen=True)
class WTLSFit:
    """One IDIM-WTLS solution at a given α, after the σ_j iteration.

    Attributes
    ----------
    alpha
        Weight of the V columns.
    column_weights
        Weight of each drive's V column: α times the noise balance of
        :func:`drive_noise_weights` (``tls.x`` holds g / column weight).
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
        Weight each drive's V column by its noise (:func:`drive_noise_weights`); False gives
        the paper's single α.
    """
    a, b = designs
    known = payload.known_mask()
    chi_known = payload.values[known]
    n, nb = a.n, a.nb
    rows_joint = a.rows + b.rows
    rows_total = rows_joint * n

    def setup(sig: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, list[tuple[int, np.ndarray]]]:
        w = alpha * (drive_noise_weights(a.kt, g, sig) if balance else np.ones(n))
        ts = [_tls_transform(d, known, chi_known, w) for d in designs]
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
        new = _floor_sigma(np.sqrt(res_sq / (rows_joint * (1.0 - (k - 1) / rows_total))))
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


@dataclass(frozen=True)
class GainIdentification:
    """IDIM-WTLS result: gains with standard deviations and the diagnostics of the method.

    Attributes
    ----------
    gains, std
        Identified drive gains (N·m/A) and one standard deviation each.
    fit
        The WTLS solution at the chosen α.
    alpha_curve
        (α, weighted relative error norm) over the grid searched; empty when α was fixed.
    sigma_initial
        σ_j from per-joint OLS with the a priori gains (the paper's first weighting), N·m.
    covariance
        Covariance of (χ, g, χ_uL) (sandwich estimate, see :func:`estimate.tls_covariance`).
    block, clusters
        Window length (samples) and number of clusters of the covariance estimate
        (:func:`wtls_covariance`).
    payload_names, payload_unknown, payload_std
        The payload parameters the WTLS identified along with the gains.
    warnings
        Ill-determination diagnostics.
    """

    gains: np.ndarray
    std: np.ndarray
    fit: WTLSFit
    alpha_curve: list[tuple[float, float]]
    sigma_initial: np.ndarray
    covariance: np.ndarray
    block: int
    clusters: int
    payload_names: list[str]
    payload_unknown: np.ndarray
    payload_std: np.ndarray
    warnings: list[str] = field(default_factory=list)

    @property
    def rel_std_percent(self) -> np.ndarray:
        return np.asarray(100.0 * self.std / np.abs(self.gains))


def _refine_grid(grid: Sequence[float], best: int, points: int = 5) -> list[float]:
    """Log-spaced points between the neighbours of the best grid point."""
    g = sorted(grid)
    lo = g[max(best - 1, 0)]
    hi = g[min(best + 1, len(g) - 1)]
    if hi <= lo:
        return []
    return [float(v) for v in np.logspace(np.log10(lo), np.log10(hi), points + 2)[1:-1]]


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
    transforms = [_tls_transform(d, known, chi_known, fit.column_weights) for d in designs]
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


def identify_gains(
    a: Design,
    b: Design,
    payload: Payload,
    apriori: np.ndarray,
    *,
    alpha: float | None = None,
    alpha_grid: Sequence[float] = DEFAULT_ALPHA_GRID,
    step: Step = _no_step,
) -> GainIdentification:
    """IDIM-WTLS identification of the drive gains from an unloaded and a loaded run.

    Parameters
    ----------
    a, b
        Designs of run a (unloaded) and run b (with ``payload``).
    payload
        The payload of run b; its ``known`` parameters set the scale.
    apriori
        A priori gains, N·m/A: only for the first σ_j (per-joint OLS, as in the paper).
    alpha
        Fixed V-column weight; None searches ``alpha_grid`` (then refines around the best).
    step
        Progress callback.

    Raises
    ------
    IdentificationError
        No finite-scale solution, or the data cannot determine the unknowns.
    """
    if not b.loaded:
        raise IdentificationError("IDIM-WTLS needs a loaded run")
    step("IDIM-WTLS: factorising")
    designs = (a, b)
    factors = (a.factors(), b.factors())
    slots = [None, 0]
    ls_t = [
        _ls_transform(d, s, 1, np.asarray(apriori)) for d, s in zip(designs, slots, strict=True)
    ]
    sigma0 = joint_sigma(designs, factors, ls_t)
    curve: list[tuple[float, float]] = []
    fits: dict[float, WTLSFit | None] = {}
    failures: list[str] = []

    def run(al: float) -> WTLSFit | None:
        if al not in fits:
            try:
                fit = wtls_fit(designs, factors, payload, al, sigma0, np.asarray(apriori))
            except IdentificationError as exc:
                # At an extreme α the scale may become unobservable; other α may be fine.
                fits[al] = None
                failures.append(f"α = {al:.3g}: {exc}")
                curve.append((al, float("nan")))
                return None
            fits[al] = fit
            curve.append((al, fit.relative_error))
        return fits[al]

    if alpha is not None:
        if not (np.isfinite(alpha) and alpha > 0):
            raise ValueError(f"alpha must be positive, got {alpha}")
        fixed = run(float(alpha))
        if fixed is None:
            raise IdentificationError(failures[-1])
        best = fixed
        curve.clear()
    else:
        grid = sorted(float(v) for v in alpha_grid)
        for i, al in enumerate(grid):
            step(f"IDIM-WTLS: α grid {i + 1}/{len(grid)}")
            run(al)
        values = [f.relative_error if f is not None else np.inf for f in (fits[g] for g in grid)]
        if not np.isfinite(min(values)):
            raise IdentificationError(f"IDIM-WTLS failed for every α: {failures[0]}")
        best_i = int(np.argmin(values))
        for al in _refine_grid(grid, best_i):
            run(al)
        best = min((f for f in fits.values() if f is not None), key=lambda f: f.relative_error)
        curve.sort()
    step("IDIM-WTLS: covariance")
    cov, block, n_clusters, warnings = wtls_covariance(designs, payload, best)
    nb, n = a.nb, a.n
    std_all = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    gains = best.gains
    std = std_all[nb : nb + n]
    if best.tls.gap < GAP_WARN:
        warnings.append(
            f"IDIM-WTLS is ill-determined: the two smallest singular values are close "
            f"(ratio {best.tls.gap:.3g} < {GAP_WARN}); excite more or use a heavier payload"
        )
    if not best.converged:
        warnings.append(f"σ_j iteration did not settle in {SIGMA_MAX_ITER} steps")
    rsd = 100.0 * std / np.abs(gains)
    for j in np.flatnonzero(rsd > GAIN_RSD_WARN):
        warnings.append(f"gain of joint {j + 1} is poorly determined (%σ = {rsd[j]:.3g} %)")
    unknown = [p for p, k in zip(PAYLOAD_PARAMS, payload.known_mask(), strict=True) if not k]
    return GainIdentification(
        gains=gains,
        std=std,
        fit=best,
        alpha_curve=curve,
        sigma_initial=sigma0,
        covariance=cov,
        block=block,
        clusters=n_clusters,
        payload_names=unknown,
        payload_unknown=best.payload_unknown,
        payload_std=std_all[nb + n :],
        warnings=warnings,
    )


# --------------------------------------------------------------------------------------------
# The whole procedure


@dataclass(frozen=True)
class GivenGains:
    """Gains given by the user (``--gains``), not identified."""

    values: np.ndarray
    std: np.ndarray | None
    source: str


@dataclass(frozen=True)
class Problem:
    """Prepared runs and model facts for one identification.

    Attributes
    ----------
    robot
        The robot description.
    bases
        Base parameters for each friction form available in the prepared runs.
    unloaded
        Run a.
    loaded
        Run b (with its payload), or None.
    validation
        A third run with a second payload, or None.
    """

    robot: Robot
    bases: dict[WristFriction, BaseParameters]
    unloaded: PreparedRun
    loaded: PreparedRun | None = None
    validation: PreparedRun | None = None


@dataclass(frozen=True)
class Options:
    """Choices of the procedure.

    Attributes
    ----------
    friction
        Coupled-wrist friction form of the main identification.
    gains
        Given gains (skip IDIM-WTLS), or None: identify when a loaded run exists, else use the
        robot's a priori gains.
    alpha
        Fixed α, or None to search ``alpha_grid``.
    cv_fraction
        Held-out fraction for the cross-validation.
    compare_forms
        Also fit the other friction form(s) and compare.
    """

    friction: WristFriction = WristFriction.PHYSICAL
    gains: GivenGains | None = None
    alpha: float | None = None
    alpha_grid: tuple[float, ...] = DEFAULT_ALPHA_GRID
    cv_fraction: float = CV_FRACTION
    compare_forms: bool = True


@dataclass(frozen=True)
class FormFit:
    """Fit quality of one coupled-wrist friction form with the final gains."""

    form: WristFriction
    case: CaseResult
    cv: CrossValidation


@dataclass(frozen=True)
class Check:
    """Physical plausibility of one identified parameter (friction, rotor inertia > 0)."""

    name: str
    value: float
    std: float
    ok: bool
    note: str


@dataclass(frozen=True)
class ProcedureResult:
    """Everything the report shows.

    Attributes
    ----------
    friction
        Friction form of the main identification.
    apriori
        A priori gains, N·m/A.
    gains_source
        ``identified`` (IDIM-WTLS), ``apriori`` or the given file.
    gains, gains_std
        Final gains and their standard deviations (None when unknown).
    wtls
        The IDIM-WTLS result, when gains were identified.
    case1
        IDIM-WLS with the a priori (or given) gains.
    case2
        IDIM-WLS with the identified gains, when identified.
    validation
        Case name -> IDIM-WLS of the validation payload with that case's gains.
    cv
        Cross-validation of the final case.
    forms
        Fit of each friction form with the final gains (Case 2 if identified, else Case 1).
    checks
        Physical plausibility of the final case's friction and rotor inertia parameters.
    samples
        Run label -> samples kept after decimation.
    warnings
        Everything a user should look at.
    """

    friction: WristFriction
    apriori: np.ndarray
    gains_source: str
    gains: np.ndarray
    gains_std: np.ndarray | None
    wtls: GainIdentification | None
    case1: CaseResult
    case2: CaseResult | None
    validation: dict[str, CaseResult]
    cv: CrossValidation
    forms: dict[WristFriction, FormFit]
    checks: list[Check]
    samples: dict[str, int]
    designs: dict[str, Design]
    warnings: list[str]

    @property
    def final(self) -> CaseResult:
        return self.case2 if self.case2 is not None else self.case1

    def better_form(self) -> WristFriction | None:
        """The friction form with the lower held-out residual, if both were fitted."""
        if len(self.forms) < 2:
            return None
        return min(self.forms.values(), key=lambda f: f.cv.relative_error).form

    def form_margin(self) -> float | None:
        """How much lower the better form's held-out residual norm is, as a fraction."""
        if len(self.forms) < 2:
            return None
        errs = sorted(f.cv.relative_error for f in self.forms.values())
        return float(1.0 - errs[0] / errs[1]) if errs[1] > 0 else 0.0


#: Parameters that must be positive when they are base parameters of their own (not regrouped).
_POSITIVE_PREFIXES = ("Ia", "Fv", "Fc", "fvm", "fcm")


def physical_checks(case: CaseResult) -> list[Check]:
    """Friction coefficients and rotor inertias identified alone must be positive."""
    out = []
    for name, v, s in zip(case.base_names, case.base, case.base_std, strict=True):
        if not name.startswith(_POSITIVE_PREFIXES) or name.endswith("R"):
            continue
        if v > 0:
            ok, note = True, ""
        elif v + 2 * s > 0:
            ok, note = False, "not positive, but within 2σ of zero"
        else:
            ok, note = False, "negative beyond 2σ: model or data problem"
        out.append(Check(name=name, value=float(v), std=float(s), ok=ok, note=note))
    return out


def run_procedure(problem: Problem, options: Options, step: Step = _no_step) -> ProcedureResult:
    """Gains (IDIM-WTLS or given), Case 1, Case 2, validation, cross-validation, checks."""
    robot = problem.robot
    form = options.friction
    if form not in problem.bases:
        raise ValueError(f"no base parameters prepared for friction form {form.value}")
    bp = problem.bases[form]
    names = list(bp.names)
    a = make_design(problem.unloaded, bp, form, robot)
    b = make_design(problem.loaded, bp, form, robot) if problem.loaded is not None else None
    if b is not None and b.run.payload is None:
        raise ValueError("the loaded run has no payload")
    if a.run.payload is not None:
        raise ValueError("run a must be unloaded")
    apriori = robot.apriori_gains
    warnings: list[str] = []
    main = [a] if b is None else [a, b]
    factors = [d.factors() for d in main]

    wtls = None
    if options.gains is not None:
        gains_source = options.gains.source
        case1_gains = options.gains.values
        step("IDIM-WLS with the given gains")
        case1 = fit_case("given", main, case1_gains, names, factors)
        case2 = None
        gains, gains_std = options.gains.values, options.gains.std
    else:
        step("Case 1: IDIM-WLS with the a priori gains")
        case1 = fit_case("case1", main, apriori, names, factors)
        if b is not None:
            assert b.run.payload is not None
            wtls = identify_gains(
                a,
                b,
                b.run.payload,
                apriori,
                alpha=options.alpha,
                alpha_grid=options.alpha_grid,
                step=step,
            )
            warnings += wtls.warnings
            step("Case 2: IDIM-WLS with the identified gains")
            case2 = fit_case("case2", main, wtls.gains, names, factors)
            gains_source, gains, gains_std = "identified", wtls.gains, wtls.std
        else:
            case2 = None
            gains_source, gains, gains_std = "apriori", apriori, None
    final = case2 if case2 is not None else case1

    validation: dict[str, CaseResult] = {}
    designs = {"unloaded": a}
    if b is not None:
        designs["loaded"] = b
    if problem.validation is not None:
        step("Validation payload (Table 5)")
        c = make_design(problem.validation, bp, form, robot)
        if c.run.payload is None:
            raise ValueError("the validation run has no payload")
        designs["validation"] = c
        validation[case1.name] = fit_case(case1.name, [a, c], case1.gains, names)
        if case2 is not None:
            validation["case2"] = fit_case("case2", [a, c], case2.gains, names)

    step("Cross-validation")
    cv = cross_validate(main, final.gains, names, options.cv_fraction)
    forms = {form: FormFit(form=form, case=final, cv=cv)}
    if options.compare_forms:
        for other, obp in problem.bases.items():
            if other is form:
                continue
            step(f"Friction form '{other.value}'")
            od = [make_design(d.run, obp, other, robot) for d in main]
            ocase = fit_case(final.name, od, final.gains, list(obp.names))
            ocv = cross_validate(od, final.gains, list(obp.names), options.cv_fraction)
            forms[other] = FormFit(form=other, case=ocase, cv=ocv)

    checks = physical_checks(final)
    for c_ in checks:
        if not c_.ok:
            warnings.append(f"{c_.name} = {c_.value:.4g} ± {c_.std:.2g}: {c_.note}")
    samples = {label: d.rows for label, d in designs.items()}
    return ProcedureResult(
        friction=form,
        apriori=apriori,
        gains_source=gains_source,
        gains=np.asarray(gains, dtype=float),
        gains_std=None if gains_std is None else np.asarray(gains_std, dtype=float),
        wtls=wtls,
        case1=case1,
        case2=case2,
        validation=validation,
        cv=cv,
        forms=forms,
        checks=checks,
        samples=samples,
        designs=designs,
        warnings=warnings,
    )
