"""Is the gains' σ honest? The default estimator alone, on more draws than the validation study.

The validation study (``benchmarks/validate.py``) runs every estimator on 100 seeds of each
scenario. A spread of z from 100 seeds is uncertain by about ±14 % (95 %), and the wrist
joints' z move together (correlation about 0.9 at 1 % current noise), so one unlucky set of
seeds shows up on three joints at once. This study runs only the default estimator (runs a and
b of each draw, the scenario's simulation) and so affords more draws, two ways:

- ``--seeds A:B``: the study's own seeds A..B−1 (each its excitation and its noise, as
  :func:`~drivegain.validation.estimators.run_seed` draws them). Printed per joint: the
  standard deviation of z = (ĝ − g)/σ̂ over the seeds with its 95 % χ² interval, the mean of z,
  and the pooled coverage of ±2σ.
- ``--trajectories T,...``: the excitation held (the scenario's trajectory seed T) and only the
  noise drawn, ``--draws`` times (scenario seeds from :data:`FIRST_DRAW`). This separates how
  well σ describes the noise on one excitation from how the estimate's bias varies between
  excitations. Printed per trajectory and joint: the scatter of the gains about their mean over
  the mean σ with its 95 % interval (1 = honest, below 1 = σ too large), the standard deviation
  of the per-draw z about its mean, the mean of z against the truth (the excitation's own bias,
  in σ), and the mean factor by which errors repeating every period raised σ
  (:attr:`~drivegain.identify.ml.MLFit.gain_repeat_scale`).

Usage: python benchmarks/study_sigma.py [--scenario random-current-1pct] --seeds 0:300
       python benchmarks/study_sigma.py [--scenario ...] --trajectories 0,1,2 [--draws 400]
       (either with [--workers 2])
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import stats

if TYPE_CHECKING:
    from drivegain.validation.scenarios import Scenario


@dataclass(frozen=True)
class Draws:
    """Identified draws of a scenario.

    Attributes
    ----------
    seeds
        The scenario seed of each draw (its noise, and without a held trajectory its
        excitation).
    failed
        Seeds whose fit failed (an :class:`~drivegain.errors.IdentificationError`), left out
        of every other field.
    trajectory
        The held trajectory seed, or None (each draw its own excitation).
    truth
        The simulation's true gains, N·m/A, (joints,).
    gains, sigma
        Each draw's identified gains and their σ, N·m/A, (draws, joints).
    repeat
        The factor the repeating errors raised each σ by, (draws, joints).
    """

    seeds: list[int]
    failed: list[int]
    trajectory: int | None
    truth: np.ndarray
    gains: np.ndarray
    sigma: np.ndarray
    repeat: np.ndarray

    @property
    def z(self) -> np.ndarray:
        """(ĝ − g)/σ̂ of every draw and joint, (draws, joints)."""
        return (self.gains - self.truth) / self.sigma


def std_interval(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Standard deviation of ``values`` (draws, joints) about their mean, and its 95 % χ²
    interval (2, joints) from ``draws − 1`` degrees of freedom (normal values)."""
    draws = values.shape[0]
    if draws < 2:
        raise ValueError(f"need 2 draws or more for a spread, got {draws}")
    std = values.std(axis=0, ddof=1)
    dof = draws - 1
    lo, hi = (np.sqrt(dof / stats.chi2.ppf(p, dof)) for p in (0.975, 0.025))
    return std, np.stack([std * lo, std * hi])


def _scenario(key: str) -> Scenario:
    from drivegain.validation.scenarios import SCENARIOS

    scenario = next((s for s in SCENARIOS if s.key == key), None)
    if scenario is None:
        raise SystemExit(f"--scenario: expected one of {', '.join(s.key for s in SCENARIOS)}")
    return scenario


def _identify(scenario_key: str, trajectory: int | None, seeds: list[int]) -> np.ndarray:
    """Identify runs a and b of each seed: rows of (gains, σ, repeat factors),
    (len(seeds), 3·joints). ``trajectory`` None: each seed on its own excitation."""
    from drivegain.errors import IdentificationError
    from drivegain.identify.blas import limited_blas_threads
    from drivegain.identify.ml import ml_fit
    from drivegain.validation.estimators import run_designs, seed_runs, seed_world
    from drivegain.validation.scenarios import scenario_rng
    from drivegain.validation.world import make_world

    scenario = _scenario(scenario_key)
    base = make_world()
    held = None if trajectory is None else seed_world(base, scenario, trajectory)
    rows = []
    with limited_blas_threads(1):
        for seed in seeds:
            world = held if held is not None else seed_world(base, scenario, seed)
            runs = seed_runs(world, scenario, scenario_rng(scenario, seed))[:2]  # runs a, b
            a, b = run_designs(world, runs)
            try:
                fit = ml_fit(a, b, world.payload)
            except IdentificationError:
                # a failed fit is a result (the study counts it), not the end of the study
                rows.append(np.full(3 * a.n, np.nan))
                continue
            scale = fit.gain_repeat_scale
            repeat = np.ones(a.n) if scale is None else scale
            rows.append(np.concatenate([fit.gains, fit.gain_std, repeat]))
    return np.array(rows)


def identify_draws(
    scenario_key: str, seeds: list[int], trajectory: int | None = None, workers: int = 1
) -> Draws:
    """Identify the draws of ``seeds`` in ``workers`` processes (the same result for any
    number); ``trajectory``: the excitation held for every draw, or None."""
    from drivegain.validation.world import load_tx40

    _scenario(scenario_key)
    if len(seeds) < 2 or workers < 1:
        raise SystemExit(
            f"need 2 draws or more and 1 worker or more, got {len(seeds)} and {workers}"
        )
    parts = [seeds[w::workers] for w in range(workers) if seeds[w::workers]]
    if len(parts) == 1:
        blocks = [_identify(scenario_key, trajectory, parts[0])]
    else:
        n = len(parts)
        with ProcessPoolExecutor(n) as pool:
            blocks = list(pool.map(_identify, [scenario_key] * n, [trajectory] * n, parts))
    rows = np.empty((len(seeds), blocks[0].shape[1]))
    for w, block in enumerate(blocks):
        rows[w::workers] = block  # back in seed order
    joints = rows.shape[1] // 3
    ok = np.all(np.isfinite(rows), axis=1)
    if ok.sum() < 2:
        raise SystemExit(f"{scenario_key}: fewer than 2 of {len(seeds)} fits succeeded")
    return Draws(
        seeds=[s for s, good in zip(seeds, ok, strict=True) if good],
        failed=[s for s, good in zip(seeds, ok, strict=True) if not good],
        trajectory=trajectory,
        truth=np.asarray(load_tx40().truth.gains, float),
        gains=rows[ok, :joints],
        sigma=rows[ok, joints : 2 * joints],
        repeat=rows[ok, 2 * joints :],
    )


def _failures(d: Draws) -> str:
    if not d.failed:
        return ""
    return f"; {len(d.failed)} fit(s) failed, left out (seeds {', '.join(map(str, d.failed))})"


def _cells(values: np.ndarray, interval: np.ndarray | None = None) -> str:
    if interval is None:
        return " | ".join(f"{v:.3f}" for v in values)
    return " | ".join(
        f"{v:.3f} [{lo:.2f}, {hi:.2f}]" for v, lo, hi in zip(values, *interval, strict=True)
    )


def _table(title: str, rows: list[tuple[str, str]], joints: int) -> None:
    print(f"| {title} | " + " | ".join(f"j{j + 1}" for j in range(joints)) + " |")
    print("|---" * (joints + 1) + "|")
    for label, cells in rows:
        print(f"| {label} | {cells} |")


def study_seeds(scenario_key: str, first: int, stop: int, workers: int = 1) -> Draws:
    """The study's seeds ``first..stop−1`` of the scenario, and their table."""
    t0 = time.perf_counter()
    d = identify_draws(scenario_key, list(range(first, stop)), None, workers)
    z = d.z
    std, interval = std_interval(z)
    coverage = float(np.mean(np.abs(z) <= 2.0))
    print(
        f"\n{scenario_key}, study seeds {first}-{stop - 1} ({len(d.seeds)}), "
        f"{time.perf_counter() - t0:.0f} s; pooled coverage of ±2σ {100 * coverage:.1f} %"
        + _failures(d)
    )
    _table(
        f"seeds {first}-{stop - 1}",
        [("std of z", _cells(std, interval)), ("mean of z", _cells(z.mean(axis=0)))],
        z.shape[1],
    )
    return d


#: Noise draws on a held trajectory use scenario seeds from here on (clear of the study's).
FIRST_DRAW = 1000


def study_trajectories(
    scenario_key: str, trajectories: list[int], draws: int, workers: int = 1
) -> list[Draws]:
    """``draws`` noise draws on each held trajectory, and their tables."""
    results = []
    seeds = list(range(FIRST_DRAW, FIRST_DRAW + draws))
    for t in trajectories:
        t0 = time.perf_counter()
        d = identify_draws(scenario_key, seeds, t, workers)
        results.append(d)
        about = d.gains - d.gains.mean(axis=0)
        scatter, interval = std_interval(about)
        mean_sigma = d.sigma.mean(axis=0)
        print(
            f"\n{scenario_key}, trajectory {t}: {draws} draws, "
            f"{time.perf_counter() - t0:.0f} s" + _failures(d)
        )
        _table(
            f"trajectory {t}",
            [
                (
                    "scatter of the gains / mean σ",
                    _cells(scatter / mean_sigma, interval / mean_sigma),
                ),
                ("std of z about its mean", _cells((about / d.sigma).std(axis=0, ddof=1))),
                ("mean z against the truth", _cells(d.z.mean(axis=0))),
                ("repeat factor, mean", _cells(d.repeat.mean(axis=0))),
            ],
            about.shape[1],
        )
    if len(results) > 1:
        ratios = [d.gains.std(axis=0, ddof=1) / d.sigma.mean(axis=0) for d in results]
        print(f"\nmean over {len(results)} trajectories of the scatter of the gains / mean σ:")
        print(" ".join(f"j{j + 1} {v:.3f}" for j, v in enumerate(np.mean(ratios, axis=0))))
    return results


def _seed_range(text: str) -> tuple[int, int]:
    try:
        first, stop = (int(v) for v in text.split(":"))
    except ValueError:
        raise SystemExit(f"--seeds: expected A:B (seeds A to B-1), got {text!r}") from None
    if not 0 <= first < stop:
        raise SystemExit(f"--seeds: expected 0 <= A < B, got {text!r}")
    return first, stop


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="random-current-1pct")
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--seeds", help="the study's seeds A:B (A to B-1)")
    which.add_argument("--trajectories", help="held trajectory seeds, comma-separated")
    parser.add_argument("--draws", type=int, default=400, help="noise draws per trajectory")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    if args.seeds is not None:
        study_seeds(args.scenario, *_seed_range(args.seeds), workers=args.workers)
        return
    try:
        trajectories = [int(t) for t in args.trajectories.split(",")]
    except ValueError:
        raise SystemExit(f"--trajectories: expected integers, got {args.trajectories!r}") from None
    study_trajectories(args.scenario, trajectories, args.draws, args.workers)


if __name__ == "__main__":
    main()
