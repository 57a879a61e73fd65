"""Where the payload's inertia bias in random closed loop comes from (issue 17 study).

In the validation study's ``random-closed-loop`` scenario the payload parameters' ±2σ cover
the truth a little less often than 95 %, and the mean of z = (χ̂ − χ)/σ̂ over the seeds is
positive on the payload's diagonal inertias (XX, YY, ZZ) while the first moments and the gains
are centred. This study runs the scenario's random excitations (our estimator only, the
payload fits of runs b and c with our gains, as the study does) on the simulated cell as it is
and on variants of its plant that each remove one suspect:

``cell``
    the scenario's plant, unchanged;
``no-coulomb``
    the truth's Coulomb friction set to zero (every joint and the coupled motor), so the
    drives never stick at a reversal;
``fine-encoder``
    motor encoders with 100 times the counts, so the positions are nearly unquantised (the
    identification sees that robot too, as a user of such a robot would).

Printed per variant, for each payload parameter: the mean and the standard deviation of z over
the seeds, and the gains' mean z. A cause shows as a mean of z that goes to about zero when it
is removed (its standard error is 1/√seeds).

Usage: python benchmarks/study_payload_bias.py [--seeds 20] [--workers 2] [--noise-free]
       [--variants cell,no-coulomb,fine-encoder]
"""

from __future__ import annotations

import argparse
import functools
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

VARIANTS = ("cell", "no-coulomb", "fine-encoder")
#: Counts per turn of the ``fine-encoder`` variant, relative to the robot file's.
FINE_ENCODER = 100

#: Per seed: variant, seed, z of payload b (10,), z of payload c (10,), z of the gains (n,).
Result = tuple[str, int, np.ndarray, np.ndarray, np.ndarray]


@functools.cache
def _world(variant: str):
    """The study's world with the plant of ``variant`` (see the module docstring)."""
    from drivegain.validation.world import make_world

    world = make_world()
    if variant == "no-coulomb":
        truth = world.truth
        links = tuple(replace(link, Fc=0.0) for link in truth.links)
        world = replace(world, truth=replace(truth, links=links, fcm=0.0))
    elif variant == "fine-encoder":
        robot = world.robot
        joints = type(robot.joints)(
            replace(j, encoder_counts=j.encoder_counts * FINE_ENCODER) for j in robot.joints
        )
        world = replace(world, robot=replace(robot, joints=joints))
    elif variant != "cell":
        raise ValueError(f"unknown variant {variant!r}; one of {', '.join(VARIANTS)}")
    return world


def _one(task: tuple[str, int, bool]) -> Result:
    """z of the payloads and gains of one seed of ``random-closed-loop`` on a variant."""
    from drivegain.identify.blas import limited_blas_threads
    from drivegain.validation.estimators import METHODS, OURS, run_seed
    from drivegain.validation.scenarios import SCENARIOS
    from drivegain.validation.statistics import payload_z

    variant, seed, noise_free = task
    sc = next(s for s in SCENARIOS if s.key == "random-closed-loop")
    if noise_free:
        sc = replace(sc, loop_noise_nm=0.0)
    world = _world(variant)
    with limited_blas_threads(1):
        res = run_seed(world, seed, sc, [m for m in METHODS if m.key == OURS])
    if OURS not in res.gains:
        raise RuntimeError(f"{variant} seed {seed}: {res.failures}")
    zb = payload_z([res], OURS, world.payload.values, "b")[0]
    # b's known parameters (its mass) scale the gains: their Case 2 values are the given ones
    zb[world.payload.known_mask()] = np.nan
    zc = payload_z([res], OURS, world.validation.values, "c")[0]
    truth = np.asarray(world.truth.gains, dtype=float)
    zg = (res.gains[OURS] - truth) / res.std[OURS]
    return variant, seed, zb, zc, zg


def _row(name: str, values: np.ndarray) -> str:
    return f"{name:26s}" + "".join(f"{v:7.2f}" for v in values)


def study(
    seeds: int, workers: int, variants: tuple[str, ...] = VARIANTS, noise_free: bool = False
) -> list[Result]:
    """Run the study and print its table (see the module docstring).

    Returns
    -------
    list of tuple
        Per variant and seed: variant, seed, z of payload b and c (10,) each (NaN where b's
        parameter is known), z of the gains (n,).

    Raises
    ------
    ValueError
        Fewer than 2 seeds, or an unknown variant.
    """
    from drivegain.config.payload import PAYLOAD_PARAMS

    if seeds < 2:
        raise ValueError(f"need 2 seeds or more, got {seeds}")
    for v in variants:
        _world(v)  # an unknown variant fails here, before any work
    tasks = [(v, s, noise_free) for v in variants for s in range(seeds)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(workers) as pool:
        out = list(pool.map(_one, tasks))
    noise = "without the current-loop noise" if noise_free else "with the current-loop noise"
    print(f"random-closed-loop {noise}, seeds 0-{seeds - 1}: z = (estimate − truth) / σ̂")
    print(f"{'':26s}" + "".join(f"{p:>7s}" for p in PAYLOAD_PARAMS))
    for v in variants:
        mine = [o for o in out if o[0] == v]
        for which, k in (("b", 2), ("c", 3)):
            z = np.array([o[k] for o in mine])
            with warnings.catch_warnings():
                # b's known mass has no z at all: its empty column is NaN, not a warning
                warnings.simplefilter("ignore", RuntimeWarning)
                print(_row(f"{v}: {which} mean", np.nanmean(z, axis=0)))
                print(_row(f"{v}: {which} std", np.nanstd(z, axis=0, ddof=1)))
        zg = np.array([o[4] for o in mine])
        print(_row(f"{v}: gains mean, j1-j{zg.shape[1]}", zg.mean(axis=0)))
    print(f"\n{len(tasks)} seeds of three recordings in {time.perf_counter() - t0:.0f} s")
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=20, help="random excitations per variant (20)")
    p.add_argument("--workers", type=int, default=2, help="processes (2)")
    p.add_argument("--noise-free", action="store_true", help="without the current-loop noise")
    p.add_argument(
        "--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}"
    )
    a = p.parse_args()
    variants = tuple(v.strip() for v in a.variants.split(",") if v.strip())
    bad = [v for v in variants if v not in VARIANTS]
    if a.seeds < 2 or a.workers < 1 or bad or not variants:
        p.error(
            "--seeds needs 2 or more, --workers 1 or more, --variants some of "
            + ", ".join(VARIANTS)
        )
    study(a.seeds, a.workers, variants, a.noise_free)


if __name__ == "__main__":
    main()
