"""Excitation optimisation of the TX-40: time to an optimised trajectory, cond against budget.

Run: ``python benchmarks/bench_excite.py [--budgets 8,16,32,64] [--payload | --no-payload]``,
or ``python benchmarks/bench_excite.py --baseline-ref [REF] [--repeats K]``: the whole command
``drivegain excite --budget 1`` of this tree beside that of REF (default c03ea6b, the release
before issue 19) installed in a temporary venv by the benchmark (benchmarks/baseline.py), with
wall and CPU time and peak RSS, and whether both wrote the same trajectory.

1. Gradient: one objective gradient by the chain rule through the regressor's state derivatives
   (what the optimiser uses) against plain finite differences of the objective (the baseline,
   1 + n(1 + 2H) objective evaluations), both in this process; ratio = baseline / ours.
2. Workers: the same optimisation (budget of the second entry of ``--budgets``) with 1 worker
   (the baseline) and with 2 workers; same trajectory (checked), ratio of wall times.
3. Budget table: for each budget, the deterministic number of starts, the wall time with 2
   workers, and what it reached: the objective minimised (log cond + log WTLS s_1/s_(p-1) with
   the payload; the best start is chosen on it, so cond alone need not fall monotonically), cond
   of the base matrix (unit-norm columns, 1000 samples per period), the WTLS s_1/s_(p-1), and the
   median cond of the random feasible starts. Wall times depend on what else runs on the
   machine; the other columns do not (the starts are deterministic).
"""

from __future__ import annotations

import argparse
import os
import time

# Single-threaded BLAS here too, as in the optimiser's workers: the in-process gradient timing
# would otherwise measure thread contention on small matrices.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from drivegain.config import load_payload, load_robot, load_truth, resource_path  # noqa: E402
from drivegain.dynamics.params import truth_vector  # noqa: E402
from drivegain.excite.evaluate import evaluate_metrics  # noqa: E402
from drivegain.excite.optimise import (  # noqa: E402
    ExcitationSettings,
    Problem,
    optimise,
    plan_budget,
)


def gradient_ratio(settings: ExcitationSettings, repeats: int = 3) -> tuple[float, float, float]:
    robot = load_robot(resource_path("tx40.toml"))
    prob = Problem(robot, settings)
    theta = prob.random_start(np.random.default_rng(0))
    ours, base = [], []
    for _ in range(repeats):
        t0 = time.process_time()
        prob._cache = None
        _, g = prob.value_and_grad(theta)
        ours.append(time.process_time() - t0)
        t0 = time.process_time()
        f0 = prob.value(theta)
        fd = np.empty_like(theta)
        for k in range(theta.size):
            e = np.zeros_like(theta)
            e[k] = 1e-6
            prob._cache = None
            fd[k] = (prob.value(theta + e) - f0) / 1e-6
        base.append(time.process_time() - t0)
    agree = float(np.linalg.norm(fd - g) / np.linalg.norm(g))
    return min(base), min(ours), agree


def compare_with_baseline(ref: str, repeats: int, budget: float = 1.0) -> None:
    """``drivegain excite --budget 1`` of this tree beside REF's, whole processes."""
    import json
    import tempfile
    from pathlib import Path

    from baseline import comparison_line, installed, now_and_then

    robot = str(resource_path("tx40.toml"))
    with tempfile.TemporaryDirectory(prefix="bench-excite-") as tmp:
        work = Path(tmp)
        with installed(ref, repeats) as base:
            now, then = now_and_then(
                base,
                ["excite", "--robot", robot, "--budget", f"{budget:g}"],
                ["--out", str(work / "now.json")],
                ["--out", str(work / "base.json")],
                repeats,
            )
            print(comparison_line(f"excite --budget {budget:g}", now, then))
        try:
            a = json.loads((work / "now.json").read_text())["fourier"]
            b = json.loads((work / "base.json").read_text())["fourier"]
            print(f"    same trajectory as the baseline: {a == b}")
        except (OSError, KeyError, ValueError) as exc:
            print(f"    trajectories not compared: {exc}")


def main() -> None:
    from baseline import add_options

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--budgets", default="8,16,32,64", help="budgets in s, comma-separated")
    parser.add_argument(
        "--payload", action=argparse.BooleanOptionalAction, default=True, help="WTLS criterion"
    )
    parser.add_argument("--seed", type=int, default=0)
    add_options(parser, "drivegain excite --budget 1 of this tree")
    args = parser.parse_args()
    if args.baseline_ref:
        compare_with_baseline(args.baseline_ref, args.repeats)
        return
    budgets = [float(b) for b in args.budgets.split(",")]
    robot = load_robot(resource_path("tx40.toml"))
    payload = chi = None
    if args.payload:
        payload = load_payload(resource_path("payloads/calibrated-4590g.toml"), robot.n)
        chi = truth_vector(robot, load_truth(resource_path("sim/tx40-truth.toml"), robot.n))
    print(f"cores: {os.cpu_count()}, load average {os.getloadavg()[0]:.2f}")

    base_settings = ExcitationSettings(payload=payload, chi_nominal=chi, seed=args.seed)
    t_fd, t_ours, agree = gradient_ratio(base_settings)
    print(
        f"\n1. gradient of the objective (CPU s): finite differences {t_fd:.3f}, chain rule "
        f"{t_ours:.3f}, ratio {t_fd / t_ours:.1f}x (relative difference {agree:.1e})"
    )

    def run(budget: float, jobs: int):
        starts, max_iter = plan_budget(budget)
        s = ExcitationSettings(
            payload=payload,
            chi_nominal=chi,
            seed=args.seed,
            starts=starts,
            max_iter=max_iter,
            jobs=jobs,
        )
        t0 = time.perf_counter()
        res = optimise(robot, s)
        return res, time.perf_counter() - t0, starts

    b_ref = budgets[1] if len(budgets) > 1 else budgets[0]
    r1, w1, starts = run(b_ref, 1)
    r2, w2, _ = run(b_ref, 2)
    same = np.array_equal(r1.fourier.coefficients(), r2.fourier.coefficients())
    print(
        f"\n2. budget {b_ref:g} s ({starts} starts): 1 worker {w1:.1f} s (baseline), 2 workers "
        f"{w2:.1f} s, ratio {w1 / w2:.2f}x; same trajectory: {same}"
    )

    print("\n3. cond reached against the budget (2 workers)")
    head = f"{'budget s':>9} {'starts':>6} {'wall s':>7} {'objective':>9} {'cond':>7}"
    head += f" {'random median':>14}"
    head += f" {'WTLS s1/s(p-1)':>15}" if payload else ""
    print(head)
    for budget in budgets:
        if budget == b_ref:
            res, wall, n_starts = r2, w2, starts
        else:
            res, wall, n_starts = run(budget, 2)
        m = evaluate_metrics(robot, res.fourier, payload=payload, chi_nominal=chi)
        line = (
            f"{budget:>9g} {n_starts:>6d} {wall:>7.1f} {res.objective:>9.4f} {m['cond']:>7.3g} "
            f"{np.median(res.random_conds):>14.3g}"
        )
        line += f" {m['wtls_cond']:>15.3g}" if payload else ""
        print(line)


if __name__ == "__main__":
    main()
