"""Where the closed-loop σ goes: the model misfit's share and the noise's (issue 17 study).

In the validation study's ``closed-loop`` scenario (one trajectory, many noise seeds) the gains'
z = (ĝ − g)/σ̂ spread far less than 1 across seeds. The seeds share the trajectory, so they
share whatever the model misses on it (the friction's state at reversals, the current's
quantisation): a bias of that trajectory, which σ̂ has to cover but the seeds' scatter cannot
show. This study splits σ̂ in two. A run of the same trajectory without the current-loop noise
leaves only that misfit: its fit reports σ̂₀ and an error of its own. With the noise,
sqrt(σ̂² − σ̂₀²) should then be the noise's part, which is what the seeds' scatter measures.
And over random excitations without noise (the ``random-closed-loop`` scenario's
trajectories), the misfit's error per σ̂₀ should spread about as N(0, 1) if σ̂ counts it right.

Printed, per joint: the noise-free run's error and σ̂₀ (% of the gain), the noisy seeds' median
σ̂, its noise part and the seeds' standard deviation; then over the noise-free random
trajectories the mean and standard deviation of error/σ̂₀ and the share within ±2σ̂₀.

Usage: python benchmarks/study_misfit.py [--seeds 40] [--trajectories 20] [--workers 2]
"""

from __future__ import annotations

import argparse
import functools
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

#: Per run: scenario key, with noise or not, seed, relative error and σ̂ of our gains.
Result = tuple[str, bool, int, np.ndarray, np.ndarray]


@functools.cache
def _world():
    from drivegain.validation.world import make_world

    return make_world()


def _one(task: tuple[str, bool, int]) -> Result:
    """Relative error and relative σ of our gains for one seed of a scenario, with or without
    its current-loop noise."""
    from drivegain.identify.blas import limited_blas_threads
    from drivegain.validation.estimators import METHODS, OURS, run_seed
    from drivegain.validation.scenarios import SCENARIOS

    key, noisy, seed = task
    sc = next(s for s in SCENARIOS if s.key == key)
    if not noisy:
        sc = replace(sc, loop_noise_nm=0.0)
    world = _world()
    truth = np.asarray(world.truth.gains, dtype=float)
    with limited_blas_threads(1):
        res = run_seed(world, seed, sc, [m for m in METHODS if m.key == OURS])
    if OURS not in res.gains:
        raise RuntimeError(f"{key} seed {seed}: {res.failures}")
    err = (res.gains[OURS] - truth) / np.abs(truth)
    return key, noisy, seed, err, res.std[OURS] / np.abs(truth)


def _row(name: str, values: np.ndarray, digits: int = 4) -> str:
    return f"{name:34s}" + "".join(f"{v:9.{digits}f}" for v in values)


def study(seeds: int, trajectories: int, workers: int) -> list[Result]:
    """Run the study and print its tables (see the module docstring).

    Returns
    -------
    list of tuple
        Per run (the noise-free ``closed-loop`` one first, then its noisy seeds, then the
        noise-free random trajectories): scenario key, with noise or not, seed, relative
        error and relative σ̂ of our gains (n,).

    Raises
    ------
    ValueError
        Fewer than 2 seeds or trajectories (no standard deviation).
    """
    if seeds < 2 or trajectories < 2:
        raise ValueError(f"need 2 seeds and 2 trajectories or more, got {seeds}, {trajectories}")
    tasks = [("closed-loop", False, 0)]
    tasks += [("closed-loop", True, s) for s in range(seeds)]
    tasks += [("random-closed-loop", False, s) for s in range(trajectories)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(workers) as pool:
        out = list(pool.map(_one, tasks))
    n = out[0][3].size
    head = f"{'':34s}" + "".join(f"{'j' + str(j + 1):>9s}" for j in range(n))
    clean = next(o for o in out if o[0] == "closed-loop" and not o[1])
    noisy = [o for o in out if o[0] == "closed-loop" and o[1]]
    err0, sd0 = 100 * clean[3], 100 * clean[4]
    errs = 100 * np.array([o[3] for o in noisy])
    sds = 100 * np.array([o[4] for o in noisy])
    sd = np.median(sds, axis=0)
    print(f"closed-loop, the shipped trajectory ({len(noisy)} noise seeds), % of each gain")
    print(head)
    print(_row("no noise: error", err0))
    print(_row("no noise: σ̂₀ (the misfit's)", sd0))
    print(_row("no noise: error / σ̂₀", err0 / sd0, 2))
    print(_row("noisy: median σ̂", sd))
    print(_row("noisy: sqrt(σ̂² − σ̂₀²) (noise part)", np.sqrt(np.clip(sd**2 - sd0**2, 0, None))))
    print(_row("noisy: seeds' std of the error", errs.std(axis=0, ddof=1)))
    print(_row("noisy: seeds' mean error", errs.mean(axis=0)))
    print(_row("noisy: std of z (σ̂ as reported)", (errs / sds).std(axis=0, ddof=1), 2))
    rand = [o for o in out if o[0] == "random-closed-loop"]
    z = np.array([o[3] / o[4] for o in rand])
    print()
    print(f"random-closed-loop without noise ({len(rand)} trajectories): error / σ̂₀")
    print(head)
    print(_row("mean", z.mean(axis=0), 2))
    print(_row("std", z.std(axis=0, ddof=1), 2))
    print(_row("within ±2σ̂₀", np.mean(np.abs(z) <= 2.0, axis=0), 2))
    print(f"\n{len(tasks)} runs of three recordings in {time.perf_counter() - t0:.0f} s")
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=40, help="noise seeds of closed-loop (40)")
    p.add_argument("--trajectories", type=int, default=20, help="random trajectories (20)")
    p.add_argument("--workers", type=int, default=2, help="processes (2)")
    a = p.parse_args()
    if a.seeds < 2 or a.trajectories < 2 or a.workers < 1:
        p.error("--seeds and --trajectories need 2 or more, --workers 1 or more")
    study(a.seeds, a.trajectories, a.workers)


if __name__ == "__main__":
    main()
