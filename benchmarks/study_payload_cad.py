"""What the payload's CAD values are worth to the gains, and what their errors cost.

The payload file says which of its 10 inertial parameters are known (``known``); drivegain
identifies the others. The mass alone fixes the scale of every gain. Listing the CAD inertia and
centre of mass as known as well removes unknowns, and on the TX-40 it is the only way for the
wrist joints' own equations to carry the scale (the payload sits on their axes). But a known
value is taken as exact: an error in it goes into the gains.

This study simulates one of the validation study's scenarios (``drivegain.validation``, the
same seeds) and identifies the gains of each seed with the payload file given five ways: the
mass known; all 10 parameters known and exact; all 10 with the inertia ``--inertia-error``
too large, then too small; all 10 with the centre of mass off by ``--com-error-mm`` along each
axis. Printed per way: the mean (bias) and the RMS over the seeds of each gain's relative
error, and the RMS over all joints.

Usage: python benchmarks/study_payload_cad.py [--seeds 30] [--scenario current-1pct]
           [--inertia-error 0.1] [--com-error-mm 1]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np


def study(
    seeds: int, scenario_key: str, inertia_error: float, com_error_mm: float
) -> dict[str, np.ndarray]:
    """Run the study and print its table (see the module docstring).

    Returns
    -------
    dict
        Each way of giving the payload → the relative gain errors, %, (seeds, joints).
    """
    from drivegain.config.payload import PAYLOAD_PARAMS
    from drivegain.identify.blas import limited_blas_threads
    from drivegain.identify.gains import Estimator, estimate_gains
    from drivegain.validation.estimators import run_designs, seed_runs, seed_world
    from drivegain.validation.scenarios import SCENARIOS, scenario_rng
    from drivegain.validation.world import make_world

    scenario = next((s for s in SCENARIOS if s.key == scenario_key), None)
    if scenario is None:
        raise SystemExit(f"--scenario: expected one of {', '.join(s.key for s in SCENARIOS)}")
    base = make_world()
    payload = base.payload
    full = replace(payload, known=PAYLOAD_PARAMS)
    inertia = slice(0, 6)  # XX..ZZ, kg·m²
    moments = slice(6, 9)  # MX, MY, MZ, kg·m
    high, low, moved = (full.values.copy() for _ in range(3))
    high[inertia] *= 1.0 + inertia_error
    low[inertia] *= 1.0 - inertia_error
    moved[moments] += payload.mass * com_error_mm * 1e-3
    ways = {
        "mass known (the file's default)": payload,
        "all 10 known, exact": full,
        f"all 10, inertia {100 * inertia_error:+g} %": replace(full, values=high),
        f"all 10, inertia {-100 * inertia_error:+g} %": replace(full, values=low),
        f"all 10, centre of mass {com_error_mm:+g} mm per axis": replace(full, values=moved),
    }
    errors: dict[str, list[np.ndarray]] = {name: [] for name in ways}
    t0 = time.perf_counter()
    with limited_blas_threads(1):
        for seed in range(seeds):
            world = seed_world(base, scenario, seed)
            runs = seed_runs(world, scenario, scenario_rng(scenario, seed))[:2]
            a, b = run_designs(world, runs)
            for name, pay in ways.items():
                res = estimate_gains(a, b, pay, world.robot.apriori_gains, estimator=Estimator.ML)
                errors[name].append(100.0 * (res.gains / world.truth.gains - 1.0))
    print(
        f"{scenario.label}: {seeds} seeds, {payload.mass:g} kg payload, "
        f"{time.perf_counter() - t0:.0f} s"
    )
    print("relative gain error, %: bias (mean over seeds) and RMS per joint; RMS over all joints")
    joints = " ".join(f"{f'j{j + 1}':>7}" for j in range(base.robot.n))
    print(f"{'payload file':<40} {'':5} {joints} {'all':>7}")
    for name, rows in errors.items():
        e = np.array(rows)
        bias, rms = e.mean(axis=0), np.sqrt((e**2).mean(axis=0))
        print(f"{name:<40} bias  " + " ".join(f"{x:+7.3f}" for x in bias))
        print(
            f"{'':<40} RMS   "
            + " ".join(f"{x:7.3f}" for x in rms)
            + f" {np.sqrt((e**2).mean()):7.3f}"
        )
    return {name: np.array(rows) for name, rows in errors.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    p.add_argument("--seeds", type=int, default=30)
    p.add_argument("--scenario", default="current-1pct", help="a validation-study scenario")
    p.add_argument("--inertia-error", type=float, default=0.1, help="relative, e.g. 0.1")
    p.add_argument("--com-error-mm", type=float, default=1.0)
    args = p.parse_args()
    if args.seeds < 1:
        p.error("--seeds must be at least 1")
    study(args.seeds, args.scenario, args.inertia_error, args.com_error_mm)


if __name__ == "__main__":
    main()
