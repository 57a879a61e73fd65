"""Drive gains by maximum likelihood in current units: the default estimator (``--estimator ml``).

The model of every sample k of every run, for the n drives at once (eq. 21 solved for the
currents)::

    v_k = diag(1/g) · K⁻¹ · (W_k χ + W_uL,k χ_uL + W_kL,k χ_kL) + e_k,    e_k ~ N(0, S_k Σ S_k)

v are the logged currents (A), g the drive gains (N·m/A), K the coupling factor of the current
matrix (:func:`~drivegain.identify.design.coupling_factor`), χ the base parameters, χ_uL the
unknown and χ_kL the known payload parameters (zero for the unloaded run). Σ (A², n × n) is the
noise model: the covariance of what the model does not explain, in current units. It is
estimated from the data together with the parameters (the profiled likelihood is
``log det Σ̂(θ)``, Σ̂(θ) the residuals' mean outer product), so no weight is chosen by hand.
S_k is diagonal, √(1 + κ_i s_ki) for drive i, s_ki the share of the sample's filter window near
a reversal of a Coulomb term of the drive (:mod:`.reversals`): a drive train that sticks at a
reversal breaks the ``Fc · sign(v)`` model there with an error of the reversal's sign, and
κ ≥ 0 (per drive, estimated from the residuals) says how much variance that adds.

Why this form: current noise (measurement noise, or torque noise turned into a current by the
controller) and model errors both add to the currents here, so neither biases the estimate;
only errors in the regressor W would, and the filtering keeps those small. The paper's
IDIM-WTLS instead spreads the errors over the V columns with a weight α that the data cannot
choose (docs/model.md, "Estimators"), and a least squares with V as regressor (the known
payload on the right-hand side) is attenuated by current noise.

The parameters are found by Gauss-Newton on the whitened residuals (the model's currents and
Jacobian are in :mod:`.mlmodel`; the steps work on the runs reduced once per κ to the R factor
of their data, :mod:`.mlreduce`, not on the samples), Σ re-estimated at every step (a coordinate
descent of the profiled likelihood, which converges to its stationary point), started from that
linear least squares; κ is estimated once, when the fit with κ = 0 has nearly settled, and held
from there. The covariance is ``H⁻¹ Jᵀ Ω̂ J H⁻¹`` with Ω̂ the whitened errors' autocovariance
over a few lags, corrected for what the fit takes out of the residuals
(:mod:`drivegain.identify.autocov`; the Newey-West estimate on the per-sample scores it replaced
was 10-20 % too small).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.optimize

from drivegain.config.payload import PAYLOAD_PARAMS, Payload
from drivegain.errors import IdentificationError, UsageError
from drivegain.identify import forked, mlreduce
from drivegain.identify.autocov import ErrorAutocovariance, LaggedSums
from drivegain.identify.design import Design, run_phases, same_phases
from drivegain.identify.eiv import InfluenceSums
from drivegain.identify.estimate import cluster_sums
from drivegain.identify.hac import bartlett_lag, gathered, lag1_autocorrelation, with_repeats
from drivegain.identify.mlmodel import (
    RunArrays,
    Whitening,
    chunks,
    neg_log_lik,
    predict,
    run_pair,
    scores,
    split_theta,
    whitened_block,
)
from drivegain.identify.mlstart import LinearStart, least_squares

#: Gauss-Newton: stop when the step moves the whitened fit by less than this (squared norm,
#: in units of the noise): the parameters then move by ~1e-5 of their standard deviations.
DECREMENT_TOL = 1e-10
#: ... and when no diagonal element of the noise covariance Σ changes by more than this.
NOISE_TOL = 1e-8
#: κ (variance near reversals) is estimated when the fit with κ = 0 moves by less than this
#: (squared, in standard deviations) and Σ by less than this relative.
KAPPA_STEP_TOL = 1e-4
MAX_ITER = 50
#: Fewest lags of the errors' autocovariance the covariance uses, decimated samples.
MIN_LAG = 6
#: Gains further than this many decades from the least-squares start mean the scale is lost
#: (least squares is attenuated by tens of percent, never by orders of magnitude).
RUNAWAY_DECADES = 4.0
#: Columns of the whitened Jacobian are dependent below this relative singular value.
RANK_TOL = 1e-10


@dataclass(frozen=True)
class MLFit:
    """Maximum-likelihood estimate of (χ, g, χ_uL) with its covariance.

    Attributes
    ----------
    chi, gains, payload_unknown
        Base parameters, drive gains (N·m/A), unknown payload parameters (SI).
    coulomb, coulomb_sources
        The reversal Coulomb coefficients, N·m (joint side), estimated beside χ, and the
        velocity of :func:`~drivegain.identify.reversals.coulomb_sources` each belongs to
        (:attr:`~drivegain.identify.prepare.PreparedRun.reversal_coulomb`; empty when the runs
        have none).
    payload_names
        Names of ``payload_unknown`` (:data:`~drivegain.config.payload.PAYLOAD_PARAMS` order).
    covariance
        Covariance of :attr:`theta` (χ, c, g, χ_uL), from the errors' autocovariance corrected
        for the fit (:mod:`~drivegain.identify.autocov`), scaled up by :attr:`repeat_scale`;
        :attr:`marginal_covariance` leaves c out.
    repeat_scale
        Per entry of :attr:`theta`, the factor (≥ 1) its standard deviation was raised by
        because the errors repeat with the excitation's period (:func:`~.hac.with_repeats`);
        None when a run spans too few periods of a known one, or has none.
    neg_log_lik
        −2 log L per sample of the fit (its noise model at the estimate, less the constant
        n·log 2π): the smaller, the better the runs' currents are explained. Comparable between
        fits of the same runs' entries (:mod:`.signchoice`).
    noise
        Σ̂, the residual covariance in current units, A², (n, n).
    kappa
        κ̂, ≥ 0, (n,): an entry of drive i with the share s of its filter window near a
        reversal of the drive's Coulomb terms has (1 + κ_i s) times the variance of one away
        from reversals (:class:`~drivegain.identify.mlmodel.Whitening`; 0 where none is).
    lag, rho
        Longest lag of the errors' autocovariance, decimated samples: :data:`MIN_LAG`, or more
        when the Newey-West rule asks for it from ``rho``, the whitened residuals' lag-1
        autocorrelation.
    autocov
        The whitened errors' autocovariance the covariance used.
    iterations, converged
        Gauss-Newton steps taken and whether the step criterion was met.
    start_gains
        Gains of the linear least-squares start (V as regressor), N·m/A.
    rows
        Scalar equations used (samples × joints over the runs).
    hessian
        H = Σ_k J̃_kᵀ J̃_k at the estimate, in :attr:`theta`'s order, the bread of the sandwich
        (kept for the errors-in-variables test, which needs the same H).
    linear
        The linear least squares that started the search (:mod:`.mlstart`; None when the
        caller gave the start).
    influence
        Long-run sum of ``linear``'s per-sample influence on the gains beside this fit's
        per-sample scores, summed in the covariance pass for the errors-in-variables test
        (:class:`.eiv.InfluenceSums`; None unless asked for).
    """

    chi: np.ndarray
    gains: np.ndarray
    payload_unknown: np.ndarray
    payload_names: list[str]
    covariance: np.ndarray
    noise: np.ndarray
    kappa: np.ndarray
    lag: int
    rho: float
    autocov: ErrorAutocovariance
    iterations: int
    converged: bool
    start_gains: np.ndarray
    rows: int
    hessian: np.ndarray
    linear: LinearStart | None = None
    influence: np.ndarray | None = None
    coulomb: np.ndarray = field(default_factory=lambda: np.zeros(0))
    coulomb_sources: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    repeat_scale: np.ndarray | None = None
    neg_log_lik: float = math.nan

    @property
    def theta(self) -> np.ndarray:
        """Every unknown, in the fit's order (χ, c, g, χ_uL)."""
        return np.concatenate([self.chi, self.coulomb, self.gains, self.payload_unknown])

    @property
    def nb(self) -> int:
        """Unknowns before the gains in :attr:`theta` (χ and c)."""
        return int(self.chi.size + self.coulomb.size)

    @property
    def std_all(self) -> np.ndarray:
        """One standard deviation of every unknown, in :attr:`theta`'s order."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    @property
    def gain_std(self) -> np.ndarray:
        return self.std_all[self.nb : self.nb + self.gains.size]

    @property
    def gain_repeat_scale(self) -> np.ndarray | None:
        """The gains' entries of :attr:`repeat_scale` (None where it is)."""
        if self.repeat_scale is None:
            return None
        return self.repeat_scale[self.nb : self.nb + self.gains.size]

    @property
    def payload_std(self) -> np.ndarray:
        return self.std_all[self.nb + self.gains.size :]

    @property
    def coulomb_std(self) -> np.ndarray:
        return self.std_all[self.chi.size : self.nb]

    @property
    def marginal_covariance(self) -> np.ndarray:
        """:attr:`covariance` of (χ, g, χ_uL) alone: the reversal Coulomb rows and columns
        left out."""
        if not self.coulomb.size:
            return self.covariance
        keep = np.r_[0 : self.chi.size, self.nb : self.covariance.shape[0]]
        return np.asarray(self.covariance[np.ix_(keep, keep)])

    @property
    def noise_std(self) -> np.ndarray:
        """Per-drive residual standard deviation in current units, A."""
        return np.sqrt(np.clip(np.diag(self.noise), 0.0, None))


#: Largest κ searched (decades): an entry wholly near reversals then counts 1e-7 of an ordinary one.
LOG_KAPPA_MAX = 7.0
#: Residual variance taken as round-off, relative to each joint's mean square current: an error
#: of 1e-8 of the signal is the arithmetic's (and a 1e-4 measurement's weight moves by 1e-8).
ROUND_OFF_VARIANCE = 1e-16


def _kappa(
    resid: Sequence[np.ndarray], runs: Sequence[RunArrays], i: int, var: float, floor: float
) -> float:
    """κ_i by maximum likelihood, drive i's variance away from reversals ``var`` held fixed.

    The entries' variance is var·(1 + κ s), s their share of reversal; κ = 0 unless a positive
    value has the larger likelihood. ``floor``: round-off variance (an exact fit gives κ = 0).
    """
    # Entries of share 0 (and runs without shares) do not depend on κ: left out of the sums.
    pairs = [
        (e[:, i], r.reversal[:, i])
        for e, r in zip(resid, runs, strict=True)
        if r.reversal is not None
    ]
    if not pairs:
        return 0.0
    share = np.concatenate([s for _, s in pairs])
    r2 = np.concatenate([e**2 for e, _ in pairs])
    r2 = np.maximum(r2, floor) / max(var, floor)
    on = share > 0.0
    if not on.any():
        return 0.0
    share, r2 = share[on], r2[on]

    def nll(log_k: float) -> float:
        f = 1.0 + 10.0**log_k * share
        return float(np.sum(np.log(f) + r2 / f))

    best = scipy.optimize.minimize_scalar(
        nll, bounds=(-3.0, LOG_KAPPA_MAX), method="bounded", options={"xatol": 1e-10}
    )
    return 10.0 ** float(best.x) if nll(float(best.x)) < float(np.sum(r2)) else 0.0


def _kappas(
    resid: Sequence[np.ndarray], runs: Sequence[RunArrays], noise: np.ndarray, floor: np.ndarray
) -> np.ndarray:
    """κ̂ of every drive (:func:`_kappa`) with the variances of ``noise`` (Σ̂ with κ = 0);
    ``floor``: each drive's round-off variance (:func:`_round_off`)."""
    var = np.diag(noise)
    return np.array([_kappa(resid, runs, i, var[i], floor[i]) for i in range(var.size)])


def _round_off(mean_square: np.ndarray) -> np.ndarray:
    """Each drive's round-off variance, A², from its mean square current ``mean_square``."""
    return np.maximum(ROUND_OFF_VARIANCE * mean_square, 1e-300)


def ml_fit(
    a: Design,
    b: Design,
    payload: Payload,
    *,
    start: np.ndarray | None = None,
    step: Callable[[str], None] | None = None,
    runs: Sequence[RunArrays] | None = None,
    parallel: bool = False,
    influence: bool = False,
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
        Starting (χ, g, χ_uL); default the linear least squares of
        :func:`~.mlstart.least_squares`, returned in :attr:`MLFit.linear`.
    step
        Progress callback (one line per phase).
    runs
        :func:`~.mlmodel.run_pair` of a and b when the caller has it already
        (built here otherwise).
    parallel
        The runs are long enough for the default start to be computed in a forked child while
        the runs are reduced at κ = 0, and for run a to be reduced (at κ = 0 and at κ̂) and its
        covariance sums built in a forked child while run b's are here (:mod:`.forked`; the
        same result either way).
    influence
        Also sum, in the covariance pass, the scores the errors-in-variables test needs
        (:attr:`MLFit.influence`; with the default start only), so that the test makes no
        pass over the samples of its own.

    Returns
    -------
    MLFit
        The estimate, its covariance and the noise model.

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
    if runs is None:
        runs = run_pair(a, b, payload)
    kt = np.asarray(a.kt, float)
    kt_inv = np.linalg.inv(kt)
    # θ = (χ, c, g, χ_uL): the runs' reversal Coulomb columns follow the base parameters
    if any(not np.array_equal(r.base_idx, runs[0].base_idx) for r in runs):
        # arrays built one run at a time with different columns: θ would mean other things
        raise UsageError("the runs' arrays have different base columns (build them by run_pair)")
    nb, n = runs[0].base_idx.size, a.n
    names = [p for p, k in zip(PAYLOAD_PARAMS, known, strict=True) if not k]
    samples = sum(r.samples for r in runs)
    floor = _round_off(np.mean(np.vstack([r.v for r in runs]) ** 2, axis=0))
    # Each step works on the runs reduced once per κ (:mod:`.mlreduce`), not on the samples.
    linear = None
    if start is None:
        # The start's pass over the samples does not need the reduction: in a forked child
        # while the runs are reduced, run a in another child (:func:`_reduce`) and run b
        # here: three parts of about the same size for two CPUs rather than one part twice
        # the others' here (the same results either way).
        pending = forked.start(
            "least-squares start", lambda: least_squares(runs, kt), parallel=parallel
        )
        try:
            reduced = _reduce(runs, kt_inv, np.zeros(n), parallel)
        except BaseException:
            pending.cancel()
            raise
        linear = pending.result()
        theta = linear.theta.copy()
    else:
        reduced = _reduce(runs, kt_inv, np.zeros(n), parallel)
        theta = np.asarray(start, float).copy()
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

    def gram_at(th: np.ndarray) -> np.ndarray:
        return mlreduce.residual_gram(reduced, th, nb, kt_inv)

    def noise(gram: np.ndarray, kappa: np.ndarray) -> Whitening:
        # Σ̂ of the scaled residuals from their Gram Σ_k ε_k ε_kᵀ. Its diagonal is floored at
        # the round-off variance: with exact (noise-free) data Σ̂ stays invertible and settles,
        # and a real estimate is not changed.
        return Whitening(np.asarray(gram / samples + np.diag(floor)), kappa)

    converged = False
    rounds = 0
    gram = gram_at(theta)  # of the runs as reduced, at θ
    whiten = noise(gram, np.zeros(n))
    # κ is estimated once, from the residuals of the fit with κ = 0 once it has (nearly)
    # settled, and then held: re-estimated with θ, it would feed on itself (entries that count
    # less are fitted less, their residuals grow, κ grows) and drift towards dropping them.
    kappa_due = any(r.reversal is not None for r in runs)
    while rounds < MAX_ITER:
        rounds += 1
        # Coordinate descent of the profiled likelihood: one Gauss-Newton step of θ with Σ
        # fixed (step halving until the whitened residuals shrink), then Σ from the new
        # residuals. Each half lowers the likelihood's negative.
        r_aug = mlreduce.augmented_factor(reduced, theta, nb, kt_inv, whiten)
        if rounds == 1:
            # The whitened Jacobian has the rank of the Jacobian (the whitening is invertible).
            _check_rank(r_aug[:-1, :-1], names, nb, n)
        r_mat, q = r_aug[:-1, :-1], r_aug[:-1, -1]
        last_r = r_mat
        delta = scipy.linalg.solve_triangular(r_mat, q)
        # ‖J̃δ‖² is how many standard deviations (squared) the fit moves.
        step_sq = float(np.sum((r_mat @ delta) ** 2))
        before = float(np.sum(q**2) + r_aug[-1, -1] ** 2)
        lam = 1.0
        while lam > 1e-6:
            trial = theta + lam * delta
            if np.all(trial[nb : nb + n] != 0.0):
                tried = gram_at(trial)
                if mlreduce.whitened_sq(tried, whiten) <= before:
                    theta, gram = trial, tried
                    break
            lam *= 0.5
        # else: no decrease along the step (round-off at the optimum): θ stays
        new = noise(gram, whiten.kappa)
        change = float(np.max(np.abs(np.diag(new.noise) / np.diag(whiten.noise) - 1.0)))
        whiten = new
        still = step_sq < DECREMENT_TOL or lam <= 1e-6
        if kappa_due and step_sq < KAPPA_STEP_TOL and change < KAPPA_STEP_TOL:
            resid = residuals(theta)
            kappa = _kappas(resid, runs, whiten.noise, floor)
            del resid
            if np.any(kappa != 0.0):
                reduced = _reduce(runs, kt_inv, kappa, parallel)
                gram = gram_at(theta)
            whiten = noise(gram, kappa)
            kappa_due = False
            continue
        if still and change < NOISE_TOL and not kappa_due:
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
        step("maximum likelihood: covariance")
    # ``whiten`` already holds Σ̂ and κ̂ of the final θ (the loop's last update).
    white = [_whitened_residuals(theta, r, kt_inv, whiten) for r in runs]  # predict chunks
    lag = bartlett_lag(white)
    rho = lag1_autocorrelation(white)
    del white
    lag = max(lag, MIN_LAG)
    # The fit's projection with the last Gauss-Newton step's H (once converged, θ moved by
    # less than 1e-5 σ since; an error in it only touches the correction for the fit, see
    # LaggedSums): one pass over the blocks, the first run's in a forked child meanwhile.
    h_inv = np.linalg.pinv(last_r.T @ last_r, hermitian=True)
    # With ``influence``, the errors-in-variables test's sums from the same blocks.
    test_ls = linear if influence else None
    phases = [run_phases(d) for d in (a, b)]
    (sums, infl, folded), *rest = forked.map_items(
        "maximum-likelihood covariance",
        lambda k: _run_sums(theta, runs[k], kt_inv, whiten, h_inv, lag, test_ls, kt, phases[k]),
        range(len(runs)),
        parallel=parallel,
    )
    by_phase = [folded]
    for other, other_infl, other_folded in rest:
        sums.merge(other)
        by_phase.append(other_folded)
        if infl is not None and other_infl is not None:
            infl.merge(other_infl)
    cov, autocov = sums.covariance()
    bread = sums.bread
    rows = sum(r.samples for r in runs) * n
    repeat = None
    summed = gathered(by_phase, same_phases([a, b]))
    if summed is not None:
        cov, repeat = with_repeats(cov, bread, summed, lag, rows)
    chi, g, chi_u = split_theta(theta, nb, n)
    sources = runs[0].base_idx[a.nb :] - len(a.run.columns)  # columns after the named ones
    return MLFit(
        chi=chi[: a.nb].copy(),
        coulomb=chi[a.nb :].copy(),
        coulomb_sources=sources.astype(np.intp),
        gains=g.copy(),
        payload_unknown=chi_u.copy(),
        payload_names=names,
        covariance=cov,
        noise=whiten.noise,
        kappa=whiten.kappa,
        lag=lag,
        rho=rho,
        autocov=autocov,
        iterations=rounds,
        converged=converged,
        start_gains=start_gains,
        rows=rows,
        hessian=bread,
        linear=linear,
        influence=None if infl is None else infl.meat(),
        repeat_scale=repeat,
        neg_log_lik=neg_log_lik(runs, whiten, gram, samples),
    )


def _run_sums(
    theta: np.ndarray,
    run: RunArrays,
    kt_inv: np.ndarray,
    whiten: Whitening,
    h_inv: np.ndarray,
    lag: int,
    linear: LinearStart | None = None,
    kt: np.ndarray | None = None,
    phases: tuple[np.ndarray, int] | None = None,
) -> tuple[LaggedSums, InfluenceSums | None, np.ndarray | None]:
    """One run's lagged sums for the covariance (:class:`~.autocov.LaggedSums`), given the
    linear start ``linear`` and the coupling factor ``kt`` the errors-in-variables test's sums
    (:class:`~.eiv.InfluenceSums`), and given its phase bins (:func:`~.hac.phase_bins`) its
    scores summed by phase, (bins, P), all from the same blocks."""
    sums = LaggedSums(h_inv, lag)
    infl = None
    if linear is not None and kt is not None:
        infl = InfluenceSums(linear, kt, lag, run.base_idx.size)
    folded = None if phases is None else np.zeros((phases[1], theta.size))
    for sl in chunks(run.samples):
        sub = run.rows(sl)
        jw, ew = whitened_block(theta, sub, kt_inv, whiten)
        sums.add(jw, ew)
        if infl is not None:
            infl.add(sub, jw, ew)
        if folded is not None and phases is not None:
            folded += cluster_sums(scores(jw, ew), phases[0][sl], phases[1])
    sums.end_run()
    if infl is not None:
        infl.end_run()
    return sums, infl, folded


def _reduce(
    runs: Sequence[RunArrays], kt_inv: np.ndarray, kappa: np.ndarray, parallel: bool = False
) -> list[mlreduce.ReducedRun]:
    """Every run reduced at ``kappa`` (:func:`.mlreduce.reduce_run`); with ``parallel`` the
    first run in a forked child (:func:`.forked.map_items`) meanwhile, with the same result."""
    return forked.map_items(
        "maximum-likelihood reduction",
        lambda r: mlreduce.reduce_run(r, kt_inv, kappa),
        runs,
        parallel=parallel,
    )


def _whitened_residuals(
    theta: np.ndarray, run: RunArrays, kt_inv: np.ndarray, whiten: Whitening
) -> np.ndarray:
    """ẽ_k = L⁻¹ S_k⁻¹ (v_k − v̂_k), (N, n) (:class:`~.mlmodel.Whitening`)."""
    return whiten.apply(run.v - predict(theta, run, kt_inv)[0], run.reversal)


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
