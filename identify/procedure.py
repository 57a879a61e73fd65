"""The paper's whole procedure on prepared runs (Gautier & Briot 2012, §3-4): orchestration.

1. Drive gains by IDIM-WTLS from run a (unloaded) and run b (known payload)
   (:func:`drivegain.identify.gains.identify_gains`; the solve and its covariance in
   :mod:`drivegain.identify.wtls`, the row and column weights in
   :mod:`drivegain.identify.weighting`).
2. Case 1 (a priori gains) and Case 2 (identified gains): IDIM-WLS of the base parameters and
   the 10 payload parameters from both runs, standard deviations by eq. (8)-(11)
   (:func:`drivegain.identify.cases.fit_case`).
3. Validation: a second payload, identified from a third run with the gains of both cases
   (Table 5).
4. Quality: error norms (Table 4), per-joint R², a held-out cross-validation
   (:mod:`drivegain.identify.crossval`), both coupled-wrist friction forms, physical
   plausibility of friction and rotor inertias (:mod:`drivegain.identify.checks`).

Two things go beyond the paper, both found necessary in simulation for honest results: the V
columns are weighted per drive (:func:`drivegain.identify.weighting.drive_noise_weights`), and
the gains' standard deviations come from a clustered sandwich covariance
(:func:`drivegain.identify.wtls.wtls_covariance`).

On long runs (:data:`~.forked.PARALLEL_EQUATIONS`), the fits that do not need each other's
results run two at a time, one in a forked child (:mod:`drivegain.identify.forked`): Case 1
beside the gains' estimation, the other friction form beside Case 2, validation and
cross-validation.
The results are identical to those of one process.

Rows of one run and one joint are reduced once to a triangular factor; every estimator works on
stacks of those small factors with row weights and column transforms
(:mod:`drivegain.identify.design`), so the α grid and the σ iteration cost almost nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivegain.config.robot import Robot, WristFriction
from drivegain.dynamics.base import BaseParameters
from drivegain.errors import InputError
from drivegain.identify import forked
from drivegain.identify.blas import limited_blas_threads
from drivegain.identify.cases import CaseResult, fit_case
from drivegain.identify.checks import Check, physical_checks
from drivegain.identify.crossval import CV_FRACTION, CrossValidation, cross_validate, split_factors
from drivegain.identify.design import Design, make_design
from drivegain.identify.gains import (
    DEFAULT_ALPHA_GRID,
    Estimator,
    GainIdentification,
    Step,
    estimate_gains,
    no_step,
)
from drivegain.identify.ml import MLFit
from drivegain.identify.prepare import PreparedRun


@dataclass(frozen=True)
class GivenGains:
    """Gains given by the user (``--gains``), not identified."""

    values: np.ndarray
    std: np.ndarray | None
    source: str


@dataclass(frozen=True)
class FitMade:
    """The maximum-likelihood fit of runs a and b, made before the procedure (the Coulomb
    sign's choice, :mod:`~drivegain.identify.signchoice`) on the designs of ``friction``.

    The gains' estimate takes it rather than fitting the same runs again when it is of the
    procedure's friction form and estimator and of the problem's own runs (the same objects:
    ``unloaded`` and ``loaded`` are the prepared runs it was made from).
    """

    friction: WristFriction
    unloaded: PreparedRun
    loaded: PreparedRun
    fit: MLFit

    def serves(self, problem: Problem, friction: WristFriction, estimator: Estimator) -> bool:
        """Whether this fit is the one the procedure would make of ``problem``."""
        return (
            self.friction is friction
            and estimator is Estimator.ML
            and self.unloaded is problem.unloaded
            and self.loaded is problem.loaded
        )


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
    gains_fit
        The maximum-likelihood fit of ``unloaded`` and ``loaded`` made already, or None.
    """

    robot: Robot
    bases: dict[WristFriction, BaseParameters]
    unloaded: PreparedRun
    loaded: PreparedRun | None = None
    validation: PreparedRun | None = None
    gains_fit: FitMade | None = None


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
    estimator
        How the gains are estimated (:class:`~drivegain.identify.gains.Estimator`).
    alpha
        Fixed α, or None to search ``alpha_grid`` (``paper`` estimator only).
    cv_fraction
        Held-out fraction for the cross-validation.
    compare_forms
        Also fit the other friction form(s) and compare.
    bootstrap
        Replicates of the ML fit's residual block bootstrap, reported beside its σ (0: none).
    """

    friction: WristFriction = WristFriction.PHYSICAL
    gains: GivenGains | None = None
    estimator: Estimator = Estimator.ML
    alpha: float | None = None
    alpha_grid: tuple[float, ...] = DEFAULT_ALPHA_GRID
    cv_fraction: float = CV_FRACTION
    compare_forms: bool = True
    bootstrap: int = 0


@dataclass(frozen=True)
class FormFit:
    """Fit quality of one coupled-wrist friction form with the final gains."""

    form: WristFriction
    case: CaseResult
    cv: CrossValidation


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


def _gain_cov(w: GainIdentification | None) -> np.ndarray | None:
    """The gains' block of the estimator's covariance, (N·m/A)², or None."""
    if w is None:
        return None
    nb = w.covariance.shape[0] - w.gains.size - w.payload_unknown.size
    return np.asarray(w.covariance[nb : nb + w.gains.size, nb : nb + w.gains.size])


def _source(run: PreparedRun) -> str | None:
    """The file a run came from, for error messages (None when it was built in memory)."""
    return run.source or None


def run_procedure(problem: Problem, options: Options, step: Step = no_step) -> ProcedureResult:
    """Gains (IDIM-WTLS or given), Case 1, Case 2, validation, cross-validation, checks.

    Parameters
    ----------
    problem
        Prepared runs and model facts.
    options
        Choices of the procedure.
    step
        Progress callback, called with a one-line description as each step starts.

    Returns
    -------
    ProcedureResult
        Everything the report shows.

    Raises
    ------
    InputError
        A run does not match its role (run a loaded, run b or the validation run without a
        payload) or the friction form has no prepared base parameters.
    IdentificationError
        The data cannot determine the unknowns.

    Notes
    -----
    OpenBLAS runs single-threaded meanwhile (:mod:`.blas`): its threads make the many small
    factorisations 10-25 times slower on busy cores, so the library call is as fast as the
    command line (which used to be the only place that set the limit).
    """
    with limited_blas_threads(1):
        return _run_procedure(problem, options, step)


def _run_procedure(problem: Problem, options: Options, step: Step) -> ProcedureResult:
    robot = problem.robot
    form = options.friction
    if form not in problem.bases:
        raise InputError(
            f"no base parameters prepared for friction form {form.value!r}", key="friction"
        )
    bp = problem.bases[form]
    names = list(bp.names)
    a = make_design(problem.unloaded, bp, form, robot)
    b = make_design(problem.loaded, bp, form, robot) if problem.loaded is not None else None
    if b is not None and b.run.payload is None:
        raise InputError(
            f"the loaded run {b.run.label!r} has no payload", file=_source(b.run), key="payload"
        )
    if a.run.payload is not None:
        raise InputError(
            f"run a ({a.run.label!r}) must be unloaded, it carries payload {a.run.payload.name!r}",
            file=_source(a.run),
            key="payload",
        )
    apriori = robot.apriori_gains
    warnings: list[str] = []
    main = [a] if b is None else [a, b]
    factors, train_factors = split_factors(main, options.cv_fraction, parallel=long_runs(main))

    wtls = None
    if options.gains is not None:
        gains_source = options.gains.source
        step("IDIM-WLS with the given gains")
        case1 = fit_case("given", main, options.gains.values, names, factors)
        gains, gains_std = options.gains.values, options.gains.std
    else:
        step("Case 1: IDIM-WLS with the a priori gains")
        # Independent of the gains: in a child while the gains are estimated, on long runs.
        pending1 = forked.start(
            "Case 1 fit",
            lambda: fit_case("case1", main, apriori, names, factors),
            parallel=b is not None and long_runs(main),
        )
        if b is not None:
            # Invariant, checked above: a loaded run always has its payload.
            assert b.run.payload is not None
            made = problem.gains_fit
            reuse = (
                made.fit
                if made is not None and made.serves(problem, form, options.estimator)
                else None
            )
            try:
                wtls = estimate_gains(
                    a,
                    b,
                    b.run.payload,
                    apriori,
                    estimator=options.estimator,
                    alpha=options.alpha,
                    alpha_grid=options.alpha_grid,
                    step=step,
                    parallel=long_runs(main),
                    bootstrap=options.bootstrap,
                    fit=reuse,
                )
            except BaseException:
                pending1.cancel()
                raise
            warnings += wtls.warnings
            gains_source, gains, gains_std = "identified", wtls.gains, wtls.std
        else:
            gains_source, gains, gains_std = "apriori", apriori, None
        case1 = pending1.result()
    final_name = "case2" if wtls is not None else case1.name

    # The other friction forms' fits need only the final gains: in a child meanwhile.
    other_forms = (
        [f for f in problem.bases if f is not form]
        if options.compare_forms and robot.couplings  # the forms differ only there
        else []
    )
    if other_forms:
        step("Friction form " + ", ".join(f"'{f.value}'" for f in other_forms))
    pending_forms = forked.start(
        "friction forms",
        lambda: {
            f: _form_fit(
                problem, f, main, final_name, gains, options.cv_fraction, (factors, train_factors)
            )
            for f in other_forms
        },
        parallel=bool(other_forms) and long_runs(main),
    )
    try:
        case2 = None
        if wtls is not None:
            step("Case 2: IDIM-WLS with the identified gains")
            case2 = fit_case(
                "case2",
                main,
                wtls.gains,
                names,
                factors,
                gain_cov=_gain_cov(wtls),
                noise=wtls.noise,
            )
        final = case2 if case2 is not None else case1
        validation, designs = _validation_fits(
            problem, form, main, factors[0], case1, case2, wtls, step
        )
        step("Cross-validation")
        cv = cross_validate(main, final.gains, names, options.cv_fraction, train_factors)
    except BaseException:
        pending_forms.cancel()
        raise
    forms = {form: FormFit(form=form, case=final, cv=cv), **pending_forms.result()}

    checks = physical_checks(final)
    for c_ in checks:
        if not c_.ok:
            warnings.append(f"{c_.name} = {c_.value:.4g} ± {2 * c_.std:.2g} (2σ): {c_.note}")
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


def long_runs(main: Sequence[Design]) -> bool:
    """The runs hold enough equations for their fits to use forked children (:mod:`.forked`)."""
    return sum(d.rows * d.n for d in main) >= forked.PARALLEL_EQUATIONS


def _form_fit(
    problem: Problem,
    form: WristFriction,
    main: list[Design],
    case: str,
    gains: np.ndarray,
    cv_fraction: float,
    main_factors: tuple[list[np.ndarray], list[np.ndarray]],
) -> FormFit:
    """The final gains' fit (named ``case``) and cross-validation with another coupled-wrist
    friction form; ``main_factors``: :func:`split_factors` of ``main``, whose joints' factors
    serve where the form changes no column (only a coupled motor's Coulomb column differs)."""
    obp = problem.bases[form]
    od = [make_design(d.run, obp, form, problem.robot) for d in main]
    names = list(obp.names)
    # in a forked child when the other forms are fitted in parallel: no fork from here
    factors, train_factors = split_factors(od, cv_fraction, like=(main, *main_factors))
    fit = fit_case(case, od, gains, names, factors)
    cv = cross_validate(od, gains, names, cv_fraction, train_factors)
    return FormFit(form=form, case=fit, cv=cv)


def _validation_fits(
    problem: Problem,
    form: WristFriction,
    main: list[Design],
    factors_a: np.ndarray,
    case1: CaseResult,
    case2: CaseResult | None,
    wtls: GainIdentification | None,
    step: Step,
) -> tuple[dict[str, CaseResult], dict[str, Design]]:
    """Table 5: the validation run's payload with the gains of each case; and the designs of
    all runs by role. ``factors_a``: run a's R factors, already computed for the main fits."""
    bp = problem.bases[form]
    names = list(bp.names)
    a = main[0]
    validation: dict[str, CaseResult] = {}
    designs = {"unloaded": a}
    if len(main) > 1:
        designs["loaded"] = main[1]
    if problem.validation is not None:
        step("Validation payload (Table 5)")
        c = make_design(problem.validation, bp, form, problem.robot)
        if c.run.payload is None:
            raise InputError(
                f"the validation run {c.run.label!r} has no payload",
                file=_source(c.run),
                key="payload",
            )
        designs["validation"] = c
        factors = [factors_a, c.factors()]  # one pass over each run for both cases
        validation[case1.name] = fit_case(case1.name, [a, c], case1.gains, names, factors)
        if case2 is not None:
            validation["case2"] = fit_case(
                "case2",
                [a, c],
                case2.gains,
                names,
                factors,
                gain_cov=_gain_cov(wtls),
                noise=None if wtls is None else wtls.noise,
            )
    return validation, designs
