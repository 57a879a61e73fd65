"""Drive gains by maximum likelihood in current units: the default estimator (``--estimator ml``).

The model of every sample k of every run, for the n drives at once (eq. 21 solved for the
currents)::

    v_k = diag(1/g) · K⁻¹ · (W_k χ + W_uL,k χ_uL + W_kL,k χ_kL) + e_k,     e_k ~ N(0, Σ)

v are the logged currents (A), g the drive gains (N·m/A), K the coupling factor of the current
matrix (:func:`~drivegain.identify.design.coupling_factor`), χ the base parameters, χ_uL the
unknown and χ_kL the known payload parameters (zero for the unloaded run). Σ (A², n × n) is the
noise model: the covariance of what the model does not explain, in current units. It is
estimated from the data together with the parameters (the profiled likelihood is
``log det Σ̂(θ)``, Σ̂(θ) the residuals' mean outer product), so no weight is chosen by hand.

Why this form: current noise (measurement noise, or torque noise turned into a current by the
controller) and model errors both add to the currents here, so neither biases the estimate;
only errors in the regressor W would, and the filtering keeps those small. The paper's
IDIM-WTLS instead spreads the errors over the V columns with a weight α that the data cannot
choose (docs/model.md, "Estimators"), and a least squares with V as regressor (the known
payload on the right-hand side) is attenuated by current noise.

The parameters are found by Gauss-Newton on the whitened residuals (normal matrix from R
factors built in row blocks), Σ re-estimated at every step (a coordinate descent of the
profiled likelihood, which converges to its stationary point), started from that linear least
squares. The covariance is the HAC sandwich of
:mod:`drivegain.identify.hac` on the per-sample scores, with the lag chosen from the whitened
residuals' autocorrelation.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from drivegain.config.payload import PAYLOAD_PARAMS, Payload
from drivegain.errors import IdentificationError
from drivegain.identify.design import Design
from drivegain.identify.estimate import r_factor
from drivegain.identify.hac import bartlett_lag, lag1_autocorrelation, long_run_covariance
from drivegain.identify.hac import sandwich as hac_sandwich

#: Gauss-Newton: stop when the step moves the whitened fit by less than this (squared norm,
#: in units of the noise): the parameters then move by ~1e-5 of their standard deviations.
DECREMENT_TOL = 1e-10
#: ... and when no diagonal element of the noise covariance Σ changes by more than this.
NOISE_TOL = 1e-8
MAX_ITER = 50
#: Gains further than this many decades from the least-squares start mean the scale is lost
#: (least squares is attenuated by tens of percent, never by orders of magnitude).
RUNAWAY_DECADES = 4.0
#: Samples per row block when building factors and scores (bounds the memory of long runs).
CHUNK = 2048
#: Columns of the whitened Jacobian are dependent below this relative singular value.
RANK_TOL = 1e-10


@dataclass(frozen=True)
class RunArrays:
    """One run's data as the ML model uses it.

    Attributes
    ----------
    v
        Currents, A, (N, n).
    w
        Base-parameter regressor per joint, (N, n, nb).
    wu
        Unknown payload parameters' columns per joint, (N, n, nu) (zero when unloaded).
    tau_known
        Torque of the known payload parameters, N·m, (N, n) (zero when unloaded).
    """

    v: np.ndarray
    w: np.ndarray
    wu: np.ndarray
    tau_known: np.ndarray

    @property
    def samples(self) -> int:
        return int(self.v.shape[0])

    def rows(self, sl: slice) -> RunArrays:
        """The samples ``sl`` (views, no copy)."""
        return RunArrays(v=self.v[sl], w=self.w[sl], wu=self.wu[sl], tau_known=self.tau_known[sl])


def run_arrays(d: Design, payload: Payload) -> RunArrays:
    """Split a design into the ML model's arrays (:class:`RunArrays`).

    Parameters
    ----------
    d
        The design of one run.
    payload
        The payload of the loaded run, whose ``known`` parameters fix the scale; an unloaded
        design gets zero payload columns of the same shape.
    """
    reg = d.run.regressor
    w = reg[:, :, d.base_idx]
    n_samples, n = w.shape[0], d.n
    mask = payload.known_mask()
    unknown = np.flatnonzero(~mask)
    if d.payload_idx is not None:
        wl = reg[:, :, d.payload_idx]
        wu = wl[:, :, unknown]
        tau_known = wl[:, :, mask] @ payload.values[mask]
    else:
        wu = np.zeros((n_samples, n, unknown.size))
        tau_known = np.zeros((n_samples, n))
    return RunArrays(v=np.asarray(d.run.current, float), w=w, wu=wu, tau_known=tau_known)


@dataclass(frozen=True)
class MLFit:
    """Maximum-likelihood estimate of (χ, g, χ_uL) with its HAC covariance.

    Attributes
    ----------
    chi, gains, payload_unknown
        Base parameters, drive gains (N·m/A), unknown payload parameters (SI).
    payload_names
        Names of ``payload_unknown`` (:data:`~drivegain.config.payload.PAYLOAD_PARAMS` order).
    covariance
        HAC covariance of (χ, g, χ_uL) in that order.
    noise
        Σ̂, the residual covariance in current units, A², (n, n).
    lag, rho
        Newey-West lag (samples) and the whitened residuals' lag-1 autocorrelation it came from.
    iterations, converged
        Gauss-Newton steps taken and whether the step criterion was met.
    start_gains
        Gains of the linear least-squares start (V as regressor), N·m/A.
    rows
        Scalar equations used (samples × joints over the runs).
    """

    chi: np.ndarray
    gains: np.ndarray
    payload_unknown: np.ndarray
    payload_names: list[str]
    covariance: np.ndarray
    noise: np.ndarray
    lag: int
    rho: float
    iterations: int
    converged: bool
    start_gains: np.ndarray
    rows: int

    @property
    def std_all(self) -> np.ndarray:
        """One standard deviation of every unknown, in (χ, g, χ_uL) order."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    @property
    def gain_std(self) -> np.ndarray:
        nb, n = self.chi.size, self.gains.size
        return self.std_all[nb : nb + n]

    @property
    def payload_std(self) -> np.ndarray:
        return self.std_all[self.chi.size + self.gains.size :]

    @property
    def noise_std(self) -> np.ndarray:
        """Per-drive residual standard deviation in current units, A."""
        return np.sqrt(np.clip(np.diag(self.noise), 0.0, None))


def _split(theta: np.ndarray, nb: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return theta[:nb], theta[nb : nb + n], theta[nb + n :]


def predict(theta: np.ndarray, run: RunArrays, kt_inv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Model currents v̂ (A, (N, n)) and the model torques mapped by K⁻¹ (N·m, (N, n))."""
    nb, n = run.w.shape[2], run.v.shape[1]
    chi, g, chi_u = _split(theta, nb, n)
    tau = run.w @ chi + run.tau_known
    if chi_u.size:
        tau = tau + run.wu @ chi_u
    u = tau @ kt_inv.T
    return u / g[None, :], u


def jacobian(theta: np.ndarray, run: RunArrays, kt_inv: np.ndarray) -> np.ndarray:
    """∂v̂/∂θ per sample, (N, n, P), θ = (χ, g, χ_uL)."""
    nb, n = run.w.shape[2], run.v.shape[1]
    g = theta[nb : nb + n]
    m = kt_inv / g[:, None]  # diag(1/g) K⁻¹
    v_hat, _ = predict(theta, run, kt_inv)
    jac = np.zeros((run.samples, n, theta.size))
    jac[:, :, :nb] = m @ run.w  # batched over samples
    idx = np.arange(n)
    jac[:, idx, nb + idx] = -v_hat / g[None, :]
    if theta.size > nb + n:
        jac[:, :, nb + n :] = m @ run.wu
    return jac


def _noise(resid: Sequence[np.ndarray]) -> np.ndarray:
    e = np.vstack(resid)
    cov = e.T @ e / e.shape[0]
    # Exact (noise-free) data: keep Σ invertible without changing a real estimate.
    floor = 1e-12 * max(float(np.trace(cov)) / cov.shape[0], 1e-300)
    return np.asarray(cov + floor * np.eye(cov.shape[0]))


def ls_rows(run: RunArrays, kt: np.ndarray) -> np.ndarray:
    """Rows ``[−W | V K | −W_uL]`` of the least squares with V as regressor, (N, n, P).

    Their product with θ = (χ, g, χ_uL) minus the known payload's torque is the equation error
    of every sample and joint, N·m.
    """
    nb, n, nu = run.w.shape[2], run.v.shape[1], run.wu.shape[2]
    m = np.zeros((run.samples, n, nb + n + nu))
    m[:, :, :nb] = -run.w
    m[:, :, nb : nb + n] = run.v[:, None, :] * kt[None, :, :]
    m[:, :, nb + n :] = -run.wu
    return m


def linear_start(runs: Sequence[RunArrays], kt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """θ of the least squares ``V K g − W χ − W_uL χ_uL = W_kL χ_kL`` (torque units).

    Rows of joint j are weighted by 1/σ_j of a first unweighted pass. With noisy currents this
    estimate is attenuated (errors in variables); it starts the likelihood search and is the
    plain LS of the errors-in-variables test. Returns θ and the row weights used, 1/(N·m).
    """
    n = runs[0].v.shape[1]
    mats = [ls_rows(r, kt) for r in runs]
    p = mats[0].shape[2]

    def system(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows_a = [(m * weights[None, :, None]).reshape(-1, p) for m in mats]
        rows_y = [(r.tau_known * weights[None, :]).reshape(-1) for r in runs]
        return np.vstack(rows_a), np.concatenate(rows_y)

    w = np.ones(n)
    a, y = system(w)
    theta, *_ = np.linalg.lstsq(a, y, rcond=None)
    sigma = np.sqrt(np.mean(((a @ theta - y).reshape(-1, n)) ** 2, axis=0))
    top = float(sigma.max())
    if top > 0.0:
        w = 1.0 / np.maximum(sigma, 1e-9 * top)
        a, y = system(w)
        theta, *_ = np.linalg.lstsq(a, y, rcond=None)
    return np.asarray(theta), w


def ml_fit(
    a: Design,
    b: Design,
    payload: Payload,
    *,
    start: np.ndarray | None = None,
    step: Callable[[str], None] | None = None,
) -> MLFit:
    """Maximum-likelihood drive gains from an unloaded run a and a loaded run b.

    Parameters
    ----------
    a, b
        Designs of run a (unloaded) and run b (carrying ``payload``).
    payload
        The payload of run b; its ``known`` parameters (at least one, e.g. the mass) set the
        scale of the solution.
    start
        Starting (χ, g, χ_uL); default the linear least squares of :func:`linear_start`.
    step
        Progress callback (one line per phase).

    Returns
    -------
    MLFit
        The estimate, its HAC covariance and the noise model.

    Raises
    ------
    IdentificationError
        Run b is not loaded, no payload parameter is known, the gains reach zero, or the runs
        do not determine the unknowns.
    """
    if not b.loaded:
        raise IdentificationError("the maximum-likelihood gains need a loaded run")
    known = payload.known_mask()
    if not known.any():
        raise IdentificationError(
            "no payload parameter is known: the scale of the gains is not determined "
            "(give at least the payload's mass)"
        )
    runs = [run_arrays(a, payload), run_arrays(b, payload)]
    kt = np.asarray(a.kt, float)
    kt_inv = np.linalg.inv(kt)
    nb, n = a.nb, a.n
    names = [p for p, k in zip(PAYLOAD_PARAMS, known, strict=True) if not k]
    theta = linear_start(runs, kt)[0] if start is None else np.asarray(start, float).copy()
    start_gains = theta[nb : nb + n].copy()
    if np.any(theta[nb : nb + n] == 0.0) or not np.all(np.isfinite(theta)):
        raise IdentificationError(
            "the least-squares start gives a zero or non-finite gain: the runs do not "
            "determine the gains (is the payload's effect in the loaded run's currents?)"
        )
    if step is not None:
        step("maximum likelihood: Gauss-Newton")

    def residuals(th: np.ndarray) -> list[np.ndarray]:
        return [r.v - predict(th, r, kt_inv)[0] for r in runs]

    def whitened_sq(th: np.ndarray, whiten: np.ndarray) -> float:
        return float(sum(np.sum((e @ whiten.T) ** 2) for e in residuals(th)))

    r_aug = _augmented_factor(theta, runs, kt_inv, np.eye(n))
    _check_rank(r_aug[:-1, :-1], names, nb, n)
    converged = False
    rounds = 0
    noise = _noise(residuals(theta))
    while rounds < MAX_ITER:
        rounds += 1
        # Coordinate descent of the profiled likelihood: one Gauss-Newton step of θ with Σ
        # fixed (step halving until the whitened residuals shrink), then Σ from the new
        # residuals. Each half lowers the likelihood's negative.
        whiten = np.linalg.inv(np.linalg.cholesky(noise))
        r_aug = _augmented_factor(theta, runs, kt_inv, whiten)
        r_mat, q = r_aug[:-1, :-1], r_aug[:-1, -1]
        delta = scipy.linalg.solve_triangular(r_mat, q)
        # ‖J̃δ‖² is how many standard deviations (squared) the fit moves.
        step_sq = float(np.sum((r_mat @ delta) ** 2))
        before = float(np.sum(q**2) + r_aug[-1, -1] ** 2)
        lam = 1.0
        while lam > 1e-6:
            trial = theta + lam * delta
            if np.all(trial[nb : nb + n] != 0.0) and whitened_sq(trial, whiten) <= before:
                break
            lam *= 0.5
        else:
            trial = theta  # no decrease along the step: round-off at the optimum
        theta = trial
        new_noise = _noise(residuals(theta))
        change = float(np.max(np.abs(np.diag(new_noise) / np.diag(noise) - 1.0)))
        noise = new_noise
        if (step_sq < DECREMENT_TOL or lam <= 1e-6) and change < NOISE_TOL:
            converged = True
            break
    if np.any(theta[nb : nb + n] == 0.0) or not np.all(np.isfinite(theta)):
        raise IdentificationError("the maximum-likelihood search gave a zero or non-finite gain")
    ratio = np.abs(theta[nb : nb + n] / start_gains)
    if float(np.max(np.abs(np.log10(ratio)))) > RUNAWAY_DECADES:
        # The likelihood keeps growing as the gains and the parameters scale up together: the
        # scale, which only the known payload parameters fix, is not in the data.
        raise IdentificationError(
            "the gains grow without bound in the maximum-likelihood search (up to "
            f"{float(ratio.max()):.2g} times the least-squares start): the loaded run's currents "
            "do not carry the known payload's effect, so the data do not fix the gains' scale"
        )
    if step is not None:
        step("maximum likelihood: HAC covariance")
    # ``noise`` is already Σ̂ of the final θ (the loop's last update).
    scores, bread, white = score_terms(theta, runs, kt_inv, noise)
    lag = bartlett_lag(white)
    rows = sum(r.samples for r in runs) * n
    cov = hac_sandwich(bread, long_run_covariance(scores, lag), rows, theta.size)
    chi, g, chi_u = _split(theta, nb, n)
    return MLFit(
        chi=chi.copy(),
        gains=g.copy(),
        payload_unknown=chi_u.copy(),
        payload_names=names,
        covariance=cov,
        noise=noise,
        lag=lag,
        rho=lag1_autocorrelation(white),
        iterations=rounds,
        converged=converged,
        start_gains=start_gains,
        rows=rows,
    )


def _augmented_factor(
    theta: np.ndarray, runs: Sequence[RunArrays], kt_inv: np.ndarray, whiten: np.ndarray
) -> np.ndarray:
    """R factor of ``[J̃ | ẽ]`` (whitened Jacobian of v̂ and residuals), built in row blocks.

    ``RᵀR = [J̃ | ẽ]ᵀ[J̃ | ẽ]``: its top-left block gives the Gauss-Newton normal matrix, its
    last column J̃ᵀẽ in the rotated basis; no tall matrix is ever held whole.
    """
    p = theta.size
    r = np.zeros((p + 1, p + 1))
    for run in runs:
        for sl in _chunks(run.samples):
            sub = run.rows(sl)
            jw = whiten @ jacobian(theta, sub, kt_inv)
            ew = (sub.v - predict(theta, sub, kt_inv)[0]) @ whiten.T
            block = np.concatenate([jw.reshape(-1, p), ew.reshape(-1, 1)], axis=1)
            r = r_factor(np.vstack([r, block]))
    return r


def _chunks(samples: int) -> list[slice]:
    return [slice(k, min(k + CHUNK, samples)) for k in range(0, samples, CHUNK)]


def score_terms(
    theta: np.ndarray, runs: Sequence[RunArrays], kt_inv: np.ndarray, noise: np.ndarray
) -> tuple[list[np.ndarray], np.ndarray, list[np.ndarray]]:
    """Per-sample scores, Gauss-Newton Hessian and whitened residuals at θ.

    Returns
    -------
    scores
        Per run, ψ_k = J̃_kᵀ ẽ_k, (N, P): θ̂ − θ ≈ H⁻¹ Σ_k ψ_k to first order.
    bread
        H = Σ_k J̃_kᵀ J̃_k, (P, P).
    white
        Per run, the whitened residuals ẽ_k = L⁻¹ (v_k − v̂_k), (N, n), Σ = L Lᵀ.
    """
    whiten = np.linalg.inv(np.linalg.cholesky(noise))
    scores, white = [], []
    bread = np.zeros((theta.size, theta.size))
    for r in runs:
        run_scores, run_white = [], []
        for sl in _chunks(r.samples):
            sub = r.rows(sl)
            jw = whiten @ jacobian(theta, sub, kt_inv)
            ew = (sub.v - predict(theta, sub, kt_inv)[0]) @ whiten.T
            run_scores.append(np.matmul(ew[:, None, :], jw)[:, 0, :])
            run_white.append(ew)
            flat = jw.reshape(-1, theta.size)
            bread += flat.T @ flat
        scores.append(np.vstack(run_scores))
        white.append(np.vstack(run_white))
    return scores, bread, white


def ml_influence(fit: MLFit, a: Design, b: Design, payload: Payload) -> list[np.ndarray]:
    """Per run, each sample's first-order contribution H⁻¹ψ_k to θ̂ − θ, (N, P).

    The influence of the fit's own data on its estimate (for tests comparing two estimators on
    the same samples, :mod:`drivegain.identify.eiv`).
    """
    runs = [run_arrays(a, payload), run_arrays(b, payload)]
    theta = np.concatenate([fit.chi, fit.gains, fit.payload_unknown])
    scores, bread, _ = score_terms(theta, runs, np.linalg.inv(a.kt), fit.noise)
    h_inv = np.linalg.pinv(bread, hermitian=True)
    return [s @ h_inv for s in scores]


def _check_rank(jac: np.ndarray, names: Sequence[str], nb: int, n: int) -> None:
    """Refuse a problem whose unknowns the data cannot separate (zero or dependent columns).

    ``jac`` is the Jacobian or its R factor (same column norms and singular values).
    """
    scale = np.linalg.norm(jac, axis=0)
    if np.any(scale == 0.0):
        raise IdentificationError(_undetermined(names, nb, n, np.flatnonzero(scale == 0.0)))
    sv = np.linalg.svd(jac / scale, compute_uv=False)
    rank = int(np.count_nonzero(sv > RANK_TOL * sv[0]))
    if rank < jac.shape[1]:
        raise IdentificationError(
            "the runs do not determine every unknown (the maximum-likelihood problem is rank "
            f"deficient: rank {rank} of {jac.shape[1]}); are the two runs different, and is the "
            "payload's effect in the loaded run's currents?"
        )


def _undetermined(names: Sequence[str], nb: int, n: int, cols: np.ndarray) -> str:
    what = []
    for c in cols:
        if c < nb:
            what.append(f"base parameter {c + 1}")
        elif c < nb + n:
            what.append(f"gain of joint {c - nb + 1}")
        else:
            what.append(f"payload parameter {names[c - nb - n]}")
    return (
        "the runs carry no information on " + ", ".join(what) + " (its column is zero): excite "
        "every joint in both runs"
    )
