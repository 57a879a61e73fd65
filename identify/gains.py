"""Drive gains by IDIM-WTLS (Gautier & Briot 2012, §3): the α search and its diagnostics.

:func:`identify_gains` takes the unloaded run a and the loaded run b, starts σ_j from a
per-joint OLS with the a priori gains (as the paper), solves IDIM-WTLS
(:func:`~drivegain.identify.wtls.wtls_fit`) over a log-spaced grid of α (the V columns'
weight), refines around the α of the smallest weighted relative error norm, and returns the
gains with their sandwich standard deviations (:func:`~drivegain.identify.wtls.wtls_covariance`)
and what a user should check: the gap between the two smallest singular values, the σ
iteration, poorly determined gains.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from drivegain.config.payload import PAYLOAD_PARAMS, Payload
from drivegain.errors import IdentificationError, InputError, UsageError
from drivegain.identify.bootstrap import BootstrapSpread, bootstrap_fit
from drivegain.identify.casenoise import CaseNoise, case_noise
from drivegain.identify.design import Design, ls_transform
from drivegain.identify.eiv import EIVTest, eiv_test
from drivegain.identify.estimate import ScaleError
from drivegain.identify.ml import MLFit, ml_fit
from drivegain.identify.mlmodel import Whitening, run_pair
from drivegain.identify.weighting import SIGMA_MAX_ITER, joint_sigma
from drivegain.identify.wtls import WTLSFit, wtls_covariance, wtls_fit

#: α grid (the V columns' weight): log-spaced, refined around the best point.
DEFAULT_ALPHA_GRID = tuple(float(a) for a in np.logspace(-4, 3, 15))
#: Warn when the two smallest singular values of the WTLS matrix are closer than this ratio.
GAP_WARN = 1.5
#: Warn when a gain's relative standard deviation exceeds this, %.
GAIN_RSD_WARN = 5.0


class Estimator(StrEnum):
    """How the gains are estimated from the unloaded and the loaded run."""

    #: Maximum likelihood in current units with an estimated noise covariance, σ from the
    #: errors' autocovariance corrected for the fit (:mod:`drivegain.identify.ml`); the default.
    ML = "ml"
    #: The paper's IDIM-WTLS with the V-column weight α searched on a grid (§3).
    PAPER = "paper"


#: Progress callback: receives a one-line description of the step starting.
Step = Callable[[str], None]


def no_step(_: str) -> None:
    """A progress callback that shows nothing."""
    return None


@dataclass(frozen=True)
class GainIdentification:
    """IDIM-WTLS result: gains with standard deviations and the diagnostics of the method.

    Attributes
    ----------
    gains, std
        Identified drive gains (N·m/A) and one standard deviation each.
    fit
        The WTLS solution at the chosen α (``--estimator paper``; None for ``ml``).
    alpha_curve
        (α, weighted relative error norm) over the grid searched; empty when α was fixed.
    sigma_initial
        σ_j from per-joint OLS with the a priori gains (the paper's first weighting), N·m
        (None for ``ml``).
    covariance
        Covariance of (χ, g, χ_uL) (sandwich estimate, see
        :func:`drivegain.identify.estimate.tls_covariance`).
    block, clusters
        Window length (samples) and number of clusters of the covariance estimate
        (:func:`~drivegain.identify.wtls.wtls_covariance`); for ``ml`` the longest lag of the
        errors' autocovariance (samples) and 0.
    payload_names, payload_unknown, payload_std
        The payload parameters the WTLS identified along with the gains.
    warnings
        Ill-determination diagnostics.
    failures
        (α, message) of every α of the search whose solve failed (reported, not only as gaps
        in ``alpha_curve``).
    estimator
        Which estimator produced the gains.
    ml, eiv
        For ``ml``: the likelihood fit (noise model, lag) and the errors-in-variables test of
        plain least squares on the same data.
    bootstrap
        For ``ml`` with ``bootstrap`` replicates asked for: their spread, a second σ
        (:mod:`~drivegain.identify.bootstrap`).
    noise
        For ``ml``: its error model, for the covariance of the fits that use its gains
        (:mod:`~drivegain.identify.casenoise`).
    """

    gains: np.ndarray
    std: np.ndarray
    fit: WTLSFit | None
    alpha_curve: list[tuple[float, float]]
    sigma_initial: np.ndarray | None
    covariance: np.ndarray
    block: int
    clusters: int
    payload_names: list[str]
    payload_unknown: np.ndarray
    payload_std: np.ndarray
    warnings: list[str] = field(default_factory=list)
    failures: list[tuple[float, str]] = field(default_factory=list)
    estimator: Estimator = Estimator.PAPER
    ml: MLFit | None = None
    eiv: EIVTest | None = None
    bootstrap: BootstrapSpread | None = None
    noise: CaseNoise | None = None

    @property
    def alpha_flatness(self) -> float | None:
        """(max − min)/min of the weighted relative error over the α searched (None if fixed).

        Near round-off (1e-8 and below) the criterion does not choose α at all: every α gives
        the same fit, and the gains barely move with it.
        """
        e = np.array([v for _, v in self.alpha_curve if np.isfinite(v)])
        if e.size < 2 or e.min() <= 0:
            return None
        return float((e.max() - e.min()) / e.min())

    @property
    def rel_std_percent(self) -> np.ndarray:
        """Relative standard deviation of each gain, %."""
        return np.asarray(100.0 * self.std / np.abs(self.gains))


def estimate_gains(
    a: Design,
    b: Design,
    payload: Payload,
    apriori: np.ndarray,
    *,
    estimator: Estimator = Estimator.ML,
    alpha: float | None = None,
    alpha_grid: Sequence[float] = DEFAULT_ALPHA_GRID,
    step: Step = no_step,
    parallel: bool = False,
    bootstrap: int = 0,
    fit: MLFit | None = None,
) -> GainIdentification:
    """Drive gains from an unloaded and a loaded run by the chosen estimator.

    ``a``, ``b``, ``payload``, ``apriori``, ``alpha``, ``alpha_grid`` and ``step`` are those of
    :func:`identify_gains` (``apriori`` and α serve the paper's estimator only); ``estimator``
    chooses :attr:`Estimator.ML` (default, :func:`~drivegain.identify.ml.ml_fit` and the
    errors-in-variables test) or :attr:`Estimator.PAPER` (:func:`identify_gains`);
    ``parallel``: the runs are long enough for the ML steps to use a forked child;
    ``bootstrap``: replicates of the ML fit's residual block bootstrap (0: none); ``fit``:
    the ML fit of these designs made already, with the test's sums (``ml_fit(a, b, payload,
    influence=True)``, as :func:`~drivegain.identify.signchoice.choose_sign` keeps it), used
    instead of fitting again (ML estimator only).

    Raises
    ------
    InputError
        ``alpha`` given with the ``ml`` estimator, or not a positive number; ``bootstrap``
        with the paper's estimator, or fewer replicates than
        :data:`~drivegain.identify.bootstrap.MIN_REPLICATES`.
    IdentificationError
        The data do not determine the gains.
    UsageError
        ``fit`` with the paper's estimator, without the test's sums, or of other runs.
    """
    if fit is not None:
        _check_fit(fit, a, b, estimator)
    if estimator is Estimator.PAPER:
        if bootstrap:
            raise InputError(
                "the bootstrap is of the maximum-likelihood fit: use it with --estimator ml",
                key="bootstrap",
            )
        return identify_gains(a, b, payload, apriori, alpha=alpha, alpha_grid=alpha_grid, step=step)
    if alpha is not None:
        raise InputError(
            "α is a weight of the paper's estimator: use it with --estimator paper", key="alpha"
        )
    # The model's arrays are built once for the fit and the test, and so is the least squares
    # (the fit's start, MLFit.linear); the fit's covariance pass also sums the test's scores.
    runs = run_pair(a, b, payload)
    if fit is None:
        fit = ml_fit(a, b, payload, step=step, runs=runs, parallel=parallel, influence=True)
    step("errors-in-variables test")
    test = eiv_test(fit, a, b, payload, runs=runs, ls=fit.linear)
    spread = None
    if bootstrap:
        step(f"bootstrap: {bootstrap} replicates")
        # Each replicate is a whole fit: on two CPUs, half of them in a forked child.
        spread = bootstrap_fit(a, b, payload, fit, bootstrap, runs=runs, parallel=True)
    noise = case_noise(
        fit.theta,
        fit.nb,
        a.kt,
        Whitening(fit.noise, fit.kappa),
        fit.autocov.gamma,
        fit.hessian,
        runs,
    )
    del runs
    warnings: list[str] = []
    if not fit.converged:
        warnings.append(
            f"maximum likelihood: Gauss-Newton did not settle in {fit.iterations} steps"
        )
    std = fit.gain_std
    warnings += _poorly_determined(fit.gains, std)
    return GainIdentification(
        gains=fit.gains,
        std=std,
        fit=None,
        alpha_curve=[],
        sigma_initial=None,
        covariance=fit.marginal_covariance,
        block=fit.lag,
        clusters=0,
        payload_names=fit.payload_names,
        payload_unknown=fit.payload_unknown,
        payload_std=fit.payload_std,
        warnings=warnings,
        estimator=Estimator.ML,
        ml=fit,
        eiv=test,
        bootstrap=spread,
        noise=noise,
    )


def _check_fit(fit: MLFit, a: Design, b: Design, estimator: Estimator) -> None:
    """Refuse a fit :func:`estimate_gains` cannot take for its own (what it can check: the
    estimator, the test's sums, the runs' size and the model's unknowns)."""
    if estimator is not Estimator.ML:
        raise UsageError("a maximum-likelihood fit was given to the paper's estimator")
    if fit.influence is None:
        raise UsageError("the given fit lacks the errors-in-variables test's sums (influence=True)")
    if fit.rows != (a.rows + b.rows) * a.n or fit.chi.size != a.nb or fit.gains.size != a.n:
        raise UsageError(
            f"the given fit is of other runs ({fit.rows} equations, {fit.chi.size} base "
            f"parameters; these runs have {(a.rows + b.rows) * a.n} and {a.nb})"
        )


def _poorly_determined(gains: np.ndarray, std: np.ndarray) -> list[str]:
    """One warning per gain whose relative standard deviation exceeds :data:`GAIN_RSD_WARN`."""
    rsd = 100.0 * std / np.abs(gains)
    return [
        f"gain of joint {j + 1} is poorly determined (%σ = {rsd[j]:.3g} %)"
        for j in np.flatnonzero(rsd > GAIN_RSD_WARN)
    ]


def _refine_grid(grid: Sequence[float], best: int, points: int = 5) -> list[float]:
    """Log-spaced points between the neighbours of the best grid point."""
    g = sorted(grid)
    lo = g[max(best - 1, 0)]
    hi = g[min(best + 1, len(g) - 1)]
    if hi <= lo:
        return []
    return [float(v) for v in np.logspace(np.log10(lo), np.log10(hi), points + 2)[1:-1]]


def identify_gains(
    a: Design,
    b: Design,
    payload: Payload,
    apriori: np.ndarray,
    *,
    alpha: float | None = None,
    alpha_grid: Sequence[float] = DEFAULT_ALPHA_GRID,
    step: Step = no_step,
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

    Returns
    -------
    GainIdentification
        Gains, standard deviations and diagnostics at the chosen α.

    Raises
    ------
    InputError
        ``alpha`` is given and not a positive number.
    IdentificationError
        Run b is not loaded, no finite-scale solution, or the data cannot determine the
        unknowns.
    """
    if not b.loaded:
        raise IdentificationError("IDIM-WTLS needs a loaded run")
    step("IDIM-WTLS: factorising")
    designs = (a, b)
    factors = (a.factors(), b.factors())
    slots = [None, 0]
    ls_t = [ls_transform(d, s, 1, np.asarray(apriori)) for d, s in zip(designs, slots, strict=True)]
    sigma0 = joint_sigma(designs, factors, ls_t)
    curve: list[tuple[float, float]] = []
    fits: dict[float, WTLSFit | None] = {}
    failures: list[tuple[float, str]] = []
    scale_only: set[float] = set()  # α whose failure is δ lost in round-off

    def run(al: float) -> WTLSFit | None:
        if al not in fits:
            try:
                fit = wtls_fit(designs, factors, payload, al, sigma0, np.asarray(apriori))
            except IdentificationError as exc:
                # At an extreme α the scale may be lost in round-off; other α may be fine.
                fits[al] = None
                failures.append((al, str(exc)))
                if isinstance(exc, ScaleError):
                    scale_only.add(al)
                curve.append((al, float("nan")))
                return None
            fits[al] = fit
            curve.append((al, fit.relative_error))
        return fits[al]

    if alpha is not None:
        if not (np.isfinite(alpha) and alpha > 0):
            raise InputError(f"must be a positive number, got {alpha}", key="alpha")
        fixed = run(float(alpha))
        if fixed is None:
            raise IdentificationError(f"IDIM-WTLS at α = {alpha:.3g}: {failures[-1][1]}")
        best = fixed
        curve.clear()
    else:
        grid = sorted(float(v) for v in alpha_grid)
        for i, al in enumerate(grid):
            step(f"IDIM-WTLS: α grid {i + 1}/{len(grid)}")
            run(al)
        values = [f.relative_error if f is not None else np.inf for f in (fits[g] for g in grid)]
        if not np.isfinite(min(values)):
            raise IdentificationError(_all_failed(failures, len(scale_only) == len(failures)))
        best_i = int(np.argmin(values))
        refine = _refine_grid(grid, best_i)
        for i, al in enumerate(refine):
            step(f"IDIM-WTLS: α refined {i + 1}/{len(refine)}")
            run(al)
        best = min((f for f in fits.values() if f is not None), key=lambda f: f.relative_error)
        curve.sort()
    step("IDIM-WTLS: covariance")
    try:
        cov, block, n_clusters, warnings = wtls_covariance(designs, payload, best)
    except IdentificationError as exc:
        raise IdentificationError(
            f"IDIM-WTLS at α = {best.alpha:.3g}: {exc}: the runs do not separate the gains "
            "from the dynamic parameters (are the two runs different, and is the payload's "
            "effect in the loaded run's currents?)"
        ) from None
    if failures:
        ok = [al for al, f in fits.items() if f is not None]
        warnings.append(
            f"IDIM-WTLS failed at {len(failures)} of {len(fits)} α "
            f"({', '.join(f'{al:.3g}' for al, _ in sorted(failures))}); solved for α in "
            f"[{min(ok):.3g}, {max(ok):.3g}]: "
            + _failure_cause(failures, len(scale_only) == len(failures))
        )
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
    warnings += _poorly_determined(gains, std)
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
        failures=sorted(failures),
    )


def _failure_cause(failures: Sequence[tuple[float, str]], scale: bool) -> str:
    """Why some α failed while others solved (the data do see the payload then)."""
    if scale:
        return (
            "there the scale component δ of the singular vector fell below round-off because "
            "of the column weight, not because the payload is unseen (other α solve)"
        )
    return "; ".join(f"α = {al:.3g}: {msg}" for al, msg in sorted(failures)[:2])


def _all_failed(failures: Sequence[tuple[float, str]], scale: bool) -> str:
    """The message when no α of the search gives a solution."""
    if scale:
        lo, hi = min(a for a, _ in failures), max(a for a, _ in failures)
        return (
            f"IDIM-WTLS has no solution with a finite scale at any α tried ({lo:.3g} to "
            f"{hi:.3g}): the singular vector's component on the known-payload column is below "
            "round-off. Either the known payload parameters are not seen by the data (check "
            "that the loaded run carries the payload, that its currents show it, and the "
            "payload file) or every α tried is too small (g/α dwarfs the scale)"
        )
    al, msg = failures[0]
    return f"IDIM-WTLS failed for every α tried (first, α = {al:.3g}: {msg})"
