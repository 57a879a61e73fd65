"""The estimators compared by the study, and the Monte Carlo that runs them seed by seed.

Every estimator of :mod:`drivegain.identify.compare` runs on the same prepared data of a seed;
each one's gains then serve a Case 2 payload fit (runs a + b and a + c), and the a priori gains
a Case 1 fit, so the payload errors of every method come from the same data too.
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
    per_joint_gains,
    tls_gains,
    wtls_gains,
)
from drivegain.identify.design import Design, make_design
from drivegain.validation.scenarios import SCENARIOS, Scenario, scenario_rng
from drivegain.validation.world import World, prepare, simulate_three


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


def _tls(a: Design, b: Design, w: World) -> GainEstimate:
    return tls_gains(a, b, w.payload)


def _per_joint(a: Design, b: Design, w: World) -> GainEstimate:
    return per_joint_gains(a, b, w.payload, known=PAYLOAD_PARAMS)


def _global_ls(a: Design, b: Design, w: World) -> GainEstimate:
    return global_ls_gains(a, b, w.payload)


def _wtls_cad(a: Design, b: Design, w: World) -> GainEstimate:
    return wtls_gains(a, b, replace(w.payload, known=PAYLOAD_PARAMS), w.robot.apriori_gains)


METHODS: tuple[Method, ...] = (
    Method(
        "wtls",
        "IDIM-WTLS (ours)",
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
        "wtls_cad",
        "IDIM-WTLS, payload CAD known",
        True,
        True,
        True,
        _wtls_cad,
        "ablation: our WTLS with all 10 payload parameters known, the information the "
        "per-joint LS uses",
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
        α chosen by our WTLS and its covariance block length, samples.
    failures
        ``"Type: message"`` of the estimators that raised.
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
    failures: dict[str, str] = field(default_factory=dict)


def run_seed(
    world: World, seed: int, scenario: Scenario, methods: Sequence[Method] = METHODS
) -> SeedResult:
    """Simulate the three runs for one seed and run every estimator on the same data."""
    rng = scenario_rng(scenario, seed)
    prepared = [prepare(world, r) for r in simulate_three(world, scenario, rng)]
    bp, form, robot = world.base, world.form, world.robot
    coupled = [make_design(p, bp, form, robot) for p in prepared]
    diagonal = [diagonal_design(d) for d in coupled]
    names = list(bp.names)
    out = SeedResult(seed=seed, scenario=scenario.key)

    def payload_fits(key: str, designs: list[Design], gains: np.ndarray) -> None:
        a, b, c = designs
        fb = fit_case(key, [a, b], gains, names)
        fc = fit_case(key, [a, c], gains, names)
        out.payload_b[key] = fb.payloads[0].values
        out.payload_b_std[key] = fb.payloads[0].std
        out.payload_c[key] = fc.payloads[0].values
        out.payload_c_std[key] = fc.payloads[0].std
        out.error_norms[key] = (fb.residual_norm, fb.relative_error, fb.sigma_rho)

    for m in methods:
        designs = coupled if m.coupled else diagonal
        t0 = time.perf_counter()
        try:
            est = m.run(designs[0], designs[1], world)
        except Exception as exc:  # a failing estimator is a result of the study, not a crash
            out.failures[m.key] = f"{type(exc).__name__}: {exc}"
            continue
        out.seconds[m.key] = time.perf_counter() - t0
        out.gains[m.key] = est.gains
        out.std[m.key] = est.std
        if m.key == "wtls":
            out.alpha = est.details.get("alpha", math.nan)
            out.block = est.details.get("block", math.nan)
        payload_fits(m.key, designs, est.gains)
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
        The simulated robot.
    seeds
        Seeds per scenario at most.
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

    Scenarios alternate seed by seed, so a budget cut leaves them with equal seed counts.
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
    futures = [[executor.submit(run_seed, world, s, sc) for sc in scenarios] for s in range(seeds)]
    for s, row in enumerate(futures):
        if s > 0 and time.perf_counter() > deadline:
            progress(f"budget spent: stopping after {s} seeds per scenario")
            for later in futures[s:]:
                for f in later:
                    f.cancel()
            break
        for sc, f in zip(scenarios, row, strict=True):
            results[sc.key].append(f.result())
        if (s + 1) % 10 == 0 or s == 0:
            per = (time.perf_counter() - t_start) / (s + 1)
            progress(f"  seed {s + 1}/{seeds} ({per:.1f} s per seed, all scenarios)")
    return results
