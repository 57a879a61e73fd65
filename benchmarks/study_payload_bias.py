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

Each payload is also fitted with the entries near reversals left out
(:func:`drivegain.identify.leaveout.near_reversals`), where a stuck drive's torque is the
model's worst: z over that fit's own σ̂, and its errors over the σ̂ of the fit on every entry.

Printed per variant, for each payload parameter: the mean and the standard deviation of z over
the seeds, the pooled ±2σ coverage, and the gains' mean z. A cause shows as a mean of z that
goes to about zero when it is removed (its standard error is 1/√seeds).

Case 2 as ``drivegain identify`` now makes it (the entries near the reversals of the drives
whose κ̂ marks them misfit left out by itself, ``leaveout.misfit_drives``) is printed too, with the
gains' κ̂ per drive.

Usage: python benchmarks/study_payload_bias.py [--seeds 20] [--workers 2] [--noise-free]
       [--variants cell,no-coulomb,fine-encoder] [--scenario random-closed-loop|closed-loop]
"""

from __future__ import annotations

import argparse
import functools
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

VARIANTS = ("cell", "no-coulomb", "fine-encoder")
#: The scenarios whose drives run in closed loop (the only ones where drives stick).
SCENARIO_KEYS = ("random-closed-loop", "closed-loop")
#: Counts per turn of the ``fine-encoder`` variant, relative to the robot file's.
FINE_ENCODER = 100


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


@dataclass(frozen=True)
class SeedZ:
    """z = (estimate − truth)/σ̂ of one seed on one variant.

    ``b``, ``c``: payloads b and c (10,) by Case 2 on every entry under the gains' error model
    (NaN for b's known mass); ``b_left``, ``c_left``: the same with the entries near every
    drive's reversals left out, over their own σ̂; ``b_left_full``, ``c_left_full``: those
    estimates' errors over the σ̂ of all entries (how much nearer the truth they are);
    ``b_case2``, ``c_case2``: by Case 2 as ``drivegain identify`` makes it (the entries near
    reversals of the drives the gains' κ̂ marks misfit left out, Newey-West σ̂); ``gains``: the
    gains (n,); ``kappa``: the gains' κ̂ per drive.
    """

    variant: str
    seed: int
    b: np.ndarray
    c: np.ndarray
    b_left: np.ndarray
    c_left: np.ndarray
    b_left_full: np.ndarray
    c_left_full: np.ndarray
    b_case2: np.ndarray
    c_case2: np.ndarray
    gains: np.ndarray
    kappa: np.ndarray


def _one(task: tuple[str, int, bool, str]) -> SeedZ:
    """z of the payloads and gains of one seed of a closed-loop scenario on a variant."""
    from drivegain.identify.blas import limited_blas_threads
    from drivegain.identify.cases import PayloadEstimate, fit_case
    from drivegain.identify.compare import ours_gains
    from drivegain.identify.design import Design
    from drivegain.identify.leaveout import near_reversals, without_rows
    from drivegain.validation.estimators import seed_designs
    from drivegain.validation.scenarios import SCENARIOS

    variant, seed, noise_free, scenario = task
    sc = next(s for s in SCENARIOS if s.key == scenario)
    if noise_free:
        sc = replace(sc, loop_noise_nm=0.0)
    world = _world(variant)
    with limited_blas_threads(1):
        # the designs validation.estimators.run_seed fits (its payload fits are redone here)
        w, (a, b, c) = seed_designs(world, sc, seed)
        est = ours_gains(a, b, w.payload, w.robot.apriori_gains)
        names = list(w.base.names)
        out: list[np.ndarray] = []
        out_case2: list[np.ndarray] = []

        def case2(designs: list[Design], **kw: bool) -> PayloadEstimate:
            fit = fit_case(
                "case2", designs, est.gains, names, gain_cov=est.gain_cov, noise=est.noise, **kw
            )
            return fit.payloads[0]

        for loaded, truth in ((b, w.payload.values), (c, w.validation.values)):
            pair = [a, loaded]
            # both under the gains' error model, as Case 2 was before it left out the
            # entries near the reversals of misfit drives by itself (leaveout.misfit_drives)
            f = case2(pair, leave_out_misfit=False)
            lo = case2([without_rows(d, near_reversals(d)) for d in pair], leave_out_misfit=False)
            out += [(f.values - truth) / f.std, (lo.values - truth) / lo.std]
            out.append((lo.values - truth) / f.std)
            dflt = case2(pair)
            out_case2.append((dflt.values - truth) / dflt.std)
    # b's known parameters (its mass) scale the gains: their Case 2 values are the given ones
    for z in [*out[:3], out_case2[0]]:
        z[world.payload.known_mask()] = np.nan
    zg = (est.gains - np.asarray(world.truth.gains, dtype=float)) / est.std
    zb, zb_left, zb_lf, zc, zc_left, zc_lf = out
    kappa = np.asarray(est.noise.whitening.kappa, dtype=float)
    return SeedZ(
        variant, seed, zb, zc, zb_left, zc_left, zb_lf, zc_lf, out_case2[0], out_case2[1], zg, kappa
    )


def _row(name: str, values: np.ndarray) -> str:
    return f"{name:34s}" + "".join(f"{v:7.2f}" for v in values)


def _coverage(z: np.ndarray) -> float:
    """Share of the finite z within ±2, %."""
    finite = z[np.isfinite(z)]
    return float(np.mean(np.abs(finite) <= 2.0) * 100.0)


def study(
    seeds: int,
    workers: int,
    variants: tuple[str, ...] = VARIANTS,
    noise_free: bool = False,
    scenario: str = "random-closed-loop",
) -> list[SeedZ]:
    """Run the study and print its table (see the module docstring).

    Returns
    -------
    list of SeedZ
        Per variant and seed.

    Raises
    ------
    ValueError
        Fewer than 2 seeds, an unknown variant or a scenario that is not a closed loop.
    """
    from drivegain.config.payload import PAYLOAD_PARAMS

    if seeds < 2:
        raise ValueError(f"need 2 seeds or more, got {seeds}")
    if scenario not in SCENARIO_KEYS:
        raise ValueError(f"scenario must be one of {', '.join(SCENARIO_KEYS)}, got {scenario!r}")
    for v in variants:
        _world(v)  # an unknown variant fails here, before any work
    tasks = [(v, s, noise_free, scenario) for v in variants for s in range(seeds)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(workers) as pool:
        out = list(pool.map(_one, tasks))
    noise = "without the current-loop noise" if noise_free else "with the current-loop noise"
    print(f"{scenario} {noise}, seeds 0-{seeds - 1}: z = (estimate − truth) / σ̂")
    print("'left out': Case 2 without the entries near reversals, z over its own σ̂;")
    print("'left out / σ̂ all': its errors over the σ̂ of the fit on every entry")
    print(f"{'':34s}" + "".join(f"{p:>7s}" for p in PAYLOAD_PARAMS))
    fields = (
        ("", "b", "c"),
        ("left out: ", "b_left", "c_left"),
        ("left out / σ̂ all: ", "b_left_full", "c_left_full"),
        ("Case 2 as identify: ", "b_case2", "c_case2"),
    )
    for v in variants:
        mine = [o for o in out if o.variant == v]
        for prefix, *names in fields:
            for which, name in zip("bc", names, strict=True):
                z = np.array([getattr(o, name) for o in mine])
                with warnings.catch_warnings():
                    # b's known mass has no z at all: its empty column is NaN, not a warning
                    warnings.simplefilter("ignore", RuntimeWarning)
                    print(_row(f"{v}: {prefix}{which} mean", np.nanmean(z, axis=0)))
                    print(_row(f"{v}: {prefix}{which} std", np.nanstd(z, axis=0, ddof=1)))
        for prefix, b, c in (fields[0], fields[1], fields[3]):
            z = np.array([np.concatenate([getattr(o, b), getattr(o, c)]) for o in mine])
            print(f"{v}: {prefix}payload ±2σ coverage {_coverage(z):.1f} %")
        kappa = np.array([o.kappa for o in mine])
        print(_row(f"{v}: gains' κ̂ median per drive", np.median(kappa, axis=0)))
        print(_row(f"{v}: gains' κ̂ smallest per drive", kappa.min(axis=0)))
        zg = np.array([o.gains for o in mine])
        print(_row(f"{v}: gains mean, j1-j{zg.shape[1]}", zg.mean(axis=0)))
    print(f"\n{len(tasks)} seeds of three recordings in {time.perf_counter() - t0:.0f} s")
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=20, help="random excitations per variant (20)")
    p.add_argument("--workers", type=int, default=2, help="processes (2)")
    p.add_argument("--noise-free", action="store_true", help="without the current-loop noise")
    p.add_argument(
        "--scenario",
        default="random-closed-loop",
        choices=SCENARIO_KEYS,
        help="the study's closed-loop scenario (random-closed-loop)",
    )
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
    study(a.seeds, a.workers, variants, a.noise_free, a.scenario)


if __name__ == "__main__":
    main()
