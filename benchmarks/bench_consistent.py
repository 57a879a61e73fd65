"""Solver time of the physically consistent fit (``identify --consistent``, issue 18).

On the real TX-40 recording (45 000 samples at 5 kHz, one unloaded run, gains = gear ratios):
the recording is converted and prepared once (not timed), then on the same prepared runs and
the same per-joint R factors:

- baseline: the unconstrained IDIM-WLS solve (:func:`drivegain.identify.cases.fit_case`),
- the consistent fit (:func:`drivegain.identify.consistent.fit_consistent`): problem building,
  cvxpy canonicalisation and the Clarabel solve, wall clock; and Clarabel's own solve time.

The first consistent fit also pays for importing cvxpy; it is reported apart. Target: the
consistent fit under 2 s.

Usage: python benchmarks/bench_consistent.py [--repeat N]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "tx40-real"
TARGET_S = 2.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="timed repetitions")
    args = parser.parse_args()
    if not (SHARED / "pos_read_data.csv").is_file():
        print(f"skipped: {SHARED} is missing (the real TX-40 recording)")
        return 0
    from drivegain.config import load_robot, resource_path
    from drivegain.dynamics.model import build_model
    from drivegain.identify.blas import limited_blas_threads
    from drivegain.identify.cases import fit_case
    from drivegain.identify.columns import bases_for_forms
    from drivegain.identify.consistent_report import load_prior
    from drivegain.identify.convert import convert_csv
    from drivegain.identify.pipeline import IdentifyRequest, run_identify

    robot_path = resource_path("tx40.toml")
    with tempfile.TemporaryDirectory() as tmp, limited_blas_threads(1):
        log = convert_csv(
            SHARED / "pos_read_data.csv",
            SHARED / "curr_data.csv",
            5000.0,
            robot_path,
            motor_side=True,
            torque=True,
            out=Path(tmp) / "tx40.mcap",
        )
        outcome = run_identify(
            IdentifyRequest(
                robot=robot_path,
                unloaded=log,
                out=Path(tmp) / "report",
                gains="gear-ratios",
                progress=False,
            )
        )
        res, robot = outcome.result, load_robot(robot_path)
        bp = bases_for_forms(build_model(robot))[res.friction]
        designs = [res.designs["unloaded"]]
        factors = [d.factors() for d in designs]
        prior, _ = load_prior(robot, None)
        final = res.final

        t0 = time.perf_counter()
        import cvxpy  # noqa: F401

        t_import = time.perf_counter() - t0
        from drivegain.identify.consistent import fit_consistent

        def consistent() -> tuple[float, float]:
            t = time.perf_counter()
            fit = fit_consistent(
                designs, bp, robot, final.gains, final.sigma_joint, prior=prior, factors=factors
            )
            return time.perf_counter() - t, fit.solve_time_s

        first, _ = consistent()
        ls_times, cons_times, solver_times = [], [], []
        for _ in range(args.repeat):
            t = time.perf_counter()
            fit_case("given", designs, final.gains, bp.names, factors)
            ls_times.append(time.perf_counter() - t)
            wall, solver = consistent()
            cons_times.append(wall)
            solver_times.append(solver)
    ls, cons, solver = (float(np.median(x)) for x in (ls_times, cons_times, solver_times))
    print(
        f"real TX-40, {res.samples['unloaded']} samples after decimation, "
        f"{bp.n_base} base parameters"
    )
    print(f"import cvxpy (once per process)           {t_import:8.3f} s")
    print(f"baseline: unconstrained IDIM-WLS solve    {ls:8.4f} s  (median of {args.repeat})")
    print(f"consistent fit, first call                {first:8.3f} s")
    print(
        f"consistent fit (build + canonicalise + solve) {cons:8.3f} s  = {cons / ls:.0f}x baseline"
    )
    print(f"  of which Clarabel's solve               {solver:8.4f} s")
    verdict = "meets" if max(first, cons) < TARGET_S else "MISSES"
    print(f"target < {TARGET_S:g} s: {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
