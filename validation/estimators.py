"""The estimators compared by the study, and the Monte Carlo that runs them seed by seed.

Every estimator of :mod:`drivegain.identify.compare` runs on the same prepared data of a seed;
each one's gains then serve a Case 2 payload fit (runs a + b and a + c), and the a priori gains
a Case 1 fit, so the payload errors of every method come from the same data too.

:data:`METHODS` lists ours first (key :data:`OURS`); the document and the statistics are generic
over the list and compare every other method with ours.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace

import numpy as np

from drivegain.config.payload import PAYLOAD_PARAMS
from drivegain.identify.cases import fit_case
from drivegain.identify.compare import (
    GainEstimate,
    diagonal_design,
    global_ls_gains,
    ours_gains,
    per_joint_gains,
    tls_gains,
    wtls_gains,
)
from drivegain.identify.design import Design, make_design
from drivegain.identify.gains import DEFAULT_ALPHA_GRID, Estimator, estimate_gains
from drivegain.identify.hac import bartlett_lag, long_run_covariance, sandwich
from drivegain.identify.maskgate import AUTO_TAPER_S, stuck_drives
from drivegain.identify.ml import ml_fit
from drivegain.identify.mlmodel import Whitening, run_pair, scores, whitened_block
from drivegain.identify.signchoice import at_position_cutoff, choose_sign, has_choice
from drivegain.validation.cell import closed_loop_three
from drivegain.validation.scenarios import (
    SCENARIOS,
    Excitation,
    Plant,
    Scenario,
    scenario_rng,
    trajectory_rng,
)
from drivegain.validation.world import (
    SimRun,
    World,
    prepare,
    random_excitation,
    simulate_three,
    with_trajectory,
)

#: Key of our estimator in :data:`METHODS` (the reference of every comparison).
OURS = "ours"
#: Key of the paper's IDIM-WTLS with its α grid (its α and block length are recorded).
PAPER = "wtls_paper"
#: A rival that needs more of the payload than its mass is compared with ours given the same:
#: per-joint LS scales the TX-40's wrist joints only from all 10 payload parameters (the mass
#: alone puts no torque on them), which a user with the payload's CAD values gives ours too
#: (``known`` in the payload file). Every other rival is compared with ours as it is.
SAME_INFORMATION = {"per_joint": "ours_cad"}


@dataclass(frozen=True)
class Method:
    """One estimator of the study.

    Attributes
    ----------
    key, label
        Short name (key of the results) and the name printed in the document.
    coupled
        Whether it models the coupled current matrix (its payload fit uses the same model as
        its gains).
    reports_std
        Whether it gives standard deviations.
    ablation
        Whether it is an ablation of ours rather than a competing method.
    run
        ``run(unloaded, loaded, world)``: the gain estimate from designs of runs a and b.
    note
        What exactly it does, for the document.
    """

    key: str
    label: str
    coupled: bool
    reports_std: bool
    ablation: bool
    run: Callable[[Design, Design, World], GainEstimate]
    note: str


def _wtls(a: Design, b: Design, w: World) -> GainEstimate:
    return wtls_gains(a, b, w.payload, w.robot.apriori_gains)


def _ours(a: Design, b: Design, w: World) -> GainEstimate:
    return ours_gains(a, b, w.payload, w.robot.apriori_gains)


def _tls(a: Design, b: Design, w: World) -> GainEstimate:
    return tls_gains(a, b, w.payload)


def _per_joint(a: Design, b: Design, w: World) -> GainEstimate:
    return per_joint_gains(a, b, w.payload, known=PAYLOAD_PARAMS)


def _global_ls(a: Design, b: Design, w: World) -> GainEstimate:
    return global_ls_gains(a, b, w.payload)


def _ours_plain(a: Design, b: Design, w: World) -> GainEstimate:
    def plain(d: Design) -> Design:
        return replace(d, run=replace(d.run, reversal_share=None))

    return ours_gains(plain(a), plain(b), w.payload, w.robot.apriori_gains)


def _ours_no_coulomb(a: Design, b: Design, w: World) -> GainEstimate:
    def without(d: Design) -> Design:
        return replace(d, run=replace(d.run, reversal_coulomb=None))

    return ours_gains(without(a), without(b), w.payload, w.robot.apriori_gains)


def _ours_newey_west(a: Design, b: Design, w: World) -> GainEstimate:
    """Our estimate with the Newey-West σ it reported before :mod:`~drivegain.identify.autocov`.

    The same fit; the covariance is the Bartlett-kernel sandwich of the per-sample scores with
    the Andrews lag and the rows/(rows − P) factor, as the ML computed it until then.
    """
    res = estimate_gains(a, b, w.payload, w.robot.apriori_gains, estimator=Estimator.ML)
    fit = res.ml
    assert fit is not None  # the ML branch always sets it
    theta = fit.theta
    kt_inv = np.linalg.inv(np.asarray(a.kt, float))
    whiten = Whitening(fit.noise, fit.kappa)
    blocks = [whitened_block(theta, r, kt_inv, whiten) for r in run_pair(a, b, w.payload)]
    lag = bartlett_lag([ew for _, ew in blocks])
    meat = long_run_covariance([scores(jw, ew) for jw, ew in blocks], lag)
    cov = sandwich(fit.hessian, meat, fit.rows, theta.size)
    g = slice(fit.nb, fit.nb + a.n)
    return GainEstimate(
        method="ML",
        gains=fit.gains,
        std=np.sqrt(np.diag(cov)[g]),
        coupled=True,
        details={"lag": float(lag)},
        gain_cov=cov[g, g],
    )


def _ours_cad(a: Design, b: Design, w: World) -> GainEstimate:
    return ours_gains(a, b, replace(w.payload, known=PAYLOAD_PARAMS), w.robot.apriori_gains)


METHODS: tuple[Method, ...] = (
    Method(
        OURS,
        "ours",
        True,
        True,
        False,
        _ours,
        "maximum likelihood in current units (the model of eq. 21 solved for the currents), "
        "noise covariance estimated with the parameters, coupled V; σ from the errors' "
        "autocovariance corrected for the fit",
    ),
    Method(
        PAPER,
        "IDIM-WTLS, paper (α grid)",
        True,
        True,
        False,
        _wtls,
        "paper §3: rows weighted by 1/σ_j (iterated on the WTLS residuals), V columns by α "
        "chosen by the weighted relative error norm, coupled V (eq. 21); sandwich σ",
    ),
    Method(
        "tls_diag",
        "TLS, unweighted, diagonal V",
        False,
        False,
        False,
        _tls,
        "same total matrix, no row weights, α = 1, and a diagonal current matrix (joint 5's "
        "equation lacks g6·v6); no σ reported",
    ),
    Method(
        "per_joint",
        "per-joint LS",
        True,
        True,
        False,
        _per_joint,
        "Gautier & Briot 2011: v_j = W_j χ/g_j + W_L,j χ_L/g_j per joint, OLS, 1/g_j the "
        "coefficient of the known payload column; all 10 payload parameters known (nominal = "
        "truth here), joint 6 solved before joint 5; σ from eq. (10)",
    ),
    Method(
        "global_ls",
        "global WLS, mass on RHS",
        True,
        True,
        False,
        _global_ls,
        "V g − W χ − W_uL χ_uL = W_kL χ_kL by LS, rows weighted by 1/σ_j iterated on its own "
        "residuals; σ from eq. (10)",
    ),
    Method(
        "tls",
        "TLS, unweighted, coupled V",
        True,
        False,
        True,
        _tls,
        "ablation: the unweighted TLS with the coupled V",
    ),
    Method(
        "ours_cad",
        "ours, payload CAD known",
        True,
        True,
        True,
        _ours_cad,
        "ablation: our estimator with all 10 payload parameters known, the information the "
        "per-joint LS uses",
    ),
    Method(
        "ours_plain",
        "ours, no reversal variance",
        True,
        True,
        True,
        _ours_plain,
        "ablation: our estimator with one variance for every entry, none apart near reversals "
        'of Coulomb friction (docs/model.md, "Reversals")',
    ),
    Method(
        "ours_no_coulomb",
        "ours, no reversal Coulomb",
        True,
        True,
        True,
        _ours_no_coulomb,
        "ablation: our estimator without the Coulomb coefficients of its own near reversals "
        '(docs/model.md, "Reversals")',
    ),
    Method(
        "ours_nw",
        "ours, Newey-West σ",
        True,
        True,
        True,
        _ours_newey_west,
        "ablation: our estimate with the Newey-West σ on the per-sample scores it reported "
        'before (docs/model.md, "Standard deviations")',
    ),
)


@dataclass
class SeedResult:
    """Everything one seed at one noise level produced (arrays per method key).

    Attributes
    ----------
    seed, scenario
        The seed and the scenario key.
    gains, std
        Estimated gains (N·m/A) and their standard deviations (``None`` if not reported).
    seconds
        Run time of each estimator, s.
    payload_b, payload_c, payload_b_std, payload_c_std
        Payload parameters (SI: kg, kg·m, kg·m²) of runs b and c fitted with each method's
        gains (key ``case1``: the a priori gains), and their standard deviations.
    error_norms
        ``(‖ρ‖ N·m, ‖ρ‖/‖Y‖, σ_ρ)`` of the fit on runs a and b.
    alpha, block
        α chosen by the paper's WTLS and its covariance block length, samples.
    details
        Each method's :attr:`GainEstimate.details` (α, grid and search diagnostics).
    at_edge
        Per method: whether a weight or α it searched ended at an end of its range (see
        :func:`search_at_edge`).
    failures
        ``"Type: message"`` of the estimators that raised.
    sign_cutoff_hz, position_cutoff_hz
        Run a's cut-off of the Coulomb columns' sign velocity as prepared (after
        :func:`run_designs`' choice) and of the positions, Hz; NaN with exact derivatives.
    left_out
        Per method: the share (0-1) of run b's Case 2 fit's entries left out near misfit
        reversals (:attr:`~drivegain.identify.cases.CaseResult.left_out`).
    """

    seed: int
    scenario: str
    gains: dict[str, np.ndarray] = field(default_factory=dict)
    std: dict[str, np.ndarray | None] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    payload_b: dict[str, np.ndarray] = field(default_factory=dict)
    payload_c: dict[str, np.ndarray] = field(default_factory=dict)
    payload_b_std: dict[str, np.ndarray] = field(default_factory=dict)
    payload_c_std: dict[str, np.ndarray] = field(default_factory=dict)
    error_norms: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    alpha: float = math.nan
    block: float = math.nan
    details: dict[str, dict[str, float]] = field(default_factory=dict)
    at_edge: dict[str, bool] = field(default_factory=dict)
    failures: dict[str, str] = field(default_factory=dict)
    sign_cutoff_hz: float = math.nan
    position_cutoff_hz: float = math.nan
    left_out: dict[str, float] = field(default_factory=dict)


def search_at_edge(details: dict[str, float]) -> bool:
    """Whether an estimate's searched weight ended at an end of its search range.

    An estimator says so itself with ``details["at_edge"]`` (non-zero: at an edge); otherwise an
    ``alpha`` in the details is compared with the ends of the paper's grid
    (:data:`~drivegain.identify.gains.DEFAULT_ALPHA_GRID`, relative tolerance 1e-4). Without
    either, nothing was searched: ``False``.
    """
    if "at_edge" in details:
        return bool(details["at_edge"])
    alpha = details.get("alpha", math.nan)
    if not math.isfinite(alpha):
        return False
    lo, hi = min(DEFAULT_ALPHA_GRID), max(DEFAULT_ALPHA_GRID)
    return bool(alpha <= lo * 1.0001 or alpha >= hi * 0.9999)


def seed_world(world: World, scenario: Scenario, seed: int) -> World:
    """The world of one seed: ``world`` itself, or with the seed's random excitation."""
    if scenario.excitation is Excitation.RANDOM:
        return with_trajectory(world, random_excitation(world, trajectory_rng(scenario, seed)))
    return world


def seed_runs(world: World, scenario: Scenario, rng: np.random.Generator) -> list[SimRun]:
    """Runs a, b, c of one seed, by exact tracking or by the closed-loop drives."""
    if scenario.plant is Plant.CLOSED_LOOP:
        return closed_loop_three(world, scenario, rng)
    return simulate_three(world, scenario, rng)


def seed_designs(world: World, scenario: Scenario, seed: int) -> tuple[World, list[Design]]:
    """The seed's world and the coupled designs of its runs a, b and c, prepared from the
    simulation: the data every estimator of :func:`run_seed` works on."""
    rng = scenario_rng(scenario, seed)
    world = seed_world(world, scenario, seed)
    return world, run_designs(world, seed_runs(world, scenario, rng))


def run_designs(world: World, runs: Sequence[SimRun]) -> list[Design]:
    """The coupled designs of simulated runs (a, b, then any others), prepared as ``identify``
    prepares logs: when the noise rule kept the Coulomb sign above the position cut-off, the
    runs are prepared with the sign at the position cut-off too and the likelier preparation of
    runs a and b is kept for all (:func:`~drivegain.identify.signchoice.choose_sign`). With
    :attr:`~.world.World.mask_auto`, then prepared again with the reversal mask on the drives
    whose κ̂ says they stick (:mod:`~drivegain.identify.maskgate`), when any does."""
    prepared = [prepare(world, r) for r in runs]
    designs = [make_design(p, world.base, world.form, world.robot) for p in prepared]
    if len(designs) < 2:
        return designs
    fit = None
    if has_choice(p.filter for p in prepared):
        # the world's own settings, as identify's second reading asks its request's again
        other = at_position_cutoff(world.settings) or world.settings
        there = replace(world, settings=other)  # prepare() sets each run's current delay
        alt = [make_design(prepare(there, r), world.base, world.form, world.robot) for r in runs]
        choice = choose_sign([(designs[0], designs[1]), (alt[0], alt[1])], world.payload)
        fit = choice.fit
        if choice.chosen != 0:
            designs, world = alt, there
    if not world.mask_auto:
        return designs
    # --reversal-mask auto: the mask on the drives whose κ̂ says they stick (maskgate)
    if fit is None:
        fit = ml_fit(designs[0], designs[1], world.payload)
    drives = stuck_drives(fit.kappa)
    if not drives:
        return designs
    masked = replace(world.settings, reversal_mask_s=AUTO_TAPER_S, reversal_mask_drives=drives)
    there = replace(world, settings=masked)
    return [make_design(prepare(there, r), world.base, world.form, world.robot) for r in runs]


def run_seed(
    world: World, seed: int, scenario: Scenario, methods: Sequence[Method] = METHODS
) -> SeedResult:
    """Simulate the three runs for one seed and run every estimator on the same data.

    A random-excitation scenario draws the seed's trajectory first (the same for runs a, b
    and c, from its own stream :func:`~drivegain.validation.scenarios.trajectory_rng`).
    """
    world, coupled = seed_designs(world, scenario, seed)
    bp, robot = world.base, world.robot
    diagonal = [diagonal_design(d) for d in coupled]
    names = list(bp.names)
    out = SeedResult(seed=seed, scenario=scenario.key)
    settings = coupled[0].run.filter
    if settings is not None:
        out.sign_cutoff_hz, out.position_cutoff_hz = settings.sign_cutoff, settings.cutoff_hz

    def payload_fits(
        key: str, designs: list[Design], gains: np.ndarray, est: GainEstimate | None = None
    ) -> None:
        a, b, c = designs
        cov = None if est is None else est.gain_cov
        noise = None if est is None else est.noise
        fb = fit_case(key, [a, b], gains, names, gain_cov=cov, noise=noise)
        fc = fit_case(key, [a, c], gains, names, gain_cov=cov, noise=noise)
        out.payload_b[key] = fb.payloads[0].values
        out.payload_b_std[key] = fb.payloads[0].std
        out.payload_c[key] = fc.payloads[0].values
        out.payload_c_std[key] = fc.payloads[0].std
        out.error_norms[key] = (fb.residual_norm, fb.relative_error, fb.sigma_rho)
        out.left_out[key] = fb.left_out / (fb.rows + fb.left_out)

    # Methods sharing a run function and a current matrix share its result (an alias).
    done: dict[tuple[int, bool], tuple[GainEstimate | str, float]] = {}
    for m in methods:
        designs = coupled if m.coupled else diagonal
        memo = (id(m.run), m.coupled)
        if memo not in done:
            t0 = time.perf_counter()
            result: GainEstimate | str
            try:
                result = m.run(designs[0], designs[1], world)
            except Exception as exc:  # a failing estimator is a result of the study, not a crash
                result = f"{type(exc).__name__}: {exc}"
            done[memo] = (result, time.perf_counter() - t0)
        est, seconds = done[memo]
        if isinstance(est, str):
            out.failures[m.key] = est
            continue
        out.seconds[m.key] = seconds
        out.gains[m.key] = est.gains
        out.std[m.key] = est.std
        out.details[m.key] = dict(est.details)
        out.at_edge[m.key] = search_at_edge(est.details)
        if m.key == PAPER:
            out.alpha = est.details.get("alpha", math.nan)
            out.block = est.details.get("block", math.nan)
        payload_fits(m.key, designs, est.gains, est)
    # Case 1: the a priori (manufacturer) gains, the true model.
    payload_fits("case1", coupled, robot.apriori_gains)
    return out


def monte_carlo(
    world: World,
    seeds: int,
    deadline: float,
    scenarios: Sequence[Scenario] = SCENARIOS,
    progress: Callable[[str], None] = print,
    executor: Executor | None = None,
) -> dict[str, list[SeedResult]]:
    """Seeds 0.. in every scenario, alternating, until ``seeds`` or the deadline.

    Parameters
    ----------
    world
        The simulated robot; with ``executor``, also anything it resolves to one (a Dask
        future of a scattered world: :mod:`~drivegain.validation.cluster`).
    seeds
        Seeds per scenario at most (a capped scenario runs :meth:`Scenario.seeds` of them).
    deadline
        :func:`time.perf_counter` value after which no new seed starts, s.
    scenarios
        Noise levels, each one of :data:`~drivegain.validation.scenarios.SCENARIOS`.
    progress
        Receives one line of progress now and then.
    executor
        Runs the (seed, scenario) pairs, e.g. a Dask client's ``get_executor()`` or a process
        pool (``world`` is pickled to it); default: one after the other here. Every pair is
        submitted at once; the results are taken seed by seed, and past the deadline the
        seeds not yet taken are cancelled.

    Scenarios alternate seed by seed, so a budget cut leaves them with equal seed counts, except
    that a scenario with a cap (:meth:`Scenario.seeds`) stops at its cap while the others go on.
    """
    if executor is not None:
        return _monte_carlo_on(executor, world, seeds, deadline, scenarios, progress)
    results: dict[str, list[SeedResult]] = {sc.key: [] for sc in scenarios}
    t_start = time.perf_counter()
    for s in range(seeds):
        if s > 0 and time.perf_counter() > deadline:
            progress(f"budget spent: stopping after {s} seeds per scenario")
            break
        for sc in scenarios:
            if s < sc.seeds(seeds):
                results[sc.key].append(run_seed(world, s, sc))
        if (s + 1) % 10 == 0 or s == 0:
            per = (time.perf_counter() - t_start) / (s + 1)
            progress(f"  seed {s + 1}/{seeds} ({per:.1f} s per seed, all scenarios)")
    return results


def _monte_carlo_on(
    executor: Executor,
    world: World,
    seeds: int,
    deadline: float,
    scenarios: Sequence[Scenario],
    progress: Callable[[str], None],
) -> dict[str, list[SeedResult]]:
    """:func:`monte_carlo` with the seeds run by ``executor`` (same results, same order)."""
    results: dict[str, list[SeedResult]] = {sc.key: [] for sc in scenarios}
    t_start = time.perf_counter()
    futures = [
        [(sc, executor.submit(run_seed, world, s, sc)) for sc in scenarios if s < sc.seeds(seeds)]
        for s in range(seeds)
    ]
    for s, row in enumerate(futures):
        if s > 0 and time.perf_counter() > deadline:
            progress(f"budget spent: stopping after {s} seeds per scenario")
            for later in futures[s:]:
                for _, f in later:
                    f.cancel()
            break
        for sc, f in row:
            results[sc.key].append(f.result())
        if (s + 1) % 10 == 0 or s == 0:
            per = (time.perf_counter() - t_start) / (s + 1)
            progress(f"  seed {s + 1}/{seeds} ({per:.1f} s per seed, all scenarios)")
    return results
