"""The validation study (issue 7): how accurate are the identified drive gains, and why.

One command, seeded:

    python benchmarks/validate.py                 # the full study, writes docs/validation.md
    python benchmarks/validate.py --quick         # 10 seeds, 1-2 minutes
    python benchmarks/validate.py --seeds 40 --budget 600 --out /tmp/study
    python benchmarks/validate.py --scheduler tcp://HOST:PORT   # the seeds on a Dask cluster
    python benchmarks/validate.py --from-results docs/validation/results.json   # the page
        again from a run's numbers, with this tree's must-show targets (no simulation)

1. Monte Carlo over noise seeds on the simulated TX-40 (simulated directly, no bus): the shipped
   optimised excitation (config/tx40-excitation.json) for run a (unloaded), run b (4.59 kg
   payload) and run c (1.686 kg payload) at two torque noise levels and with current noise of
   1 % of rated current, torque noise entering through the current references, encoder
   quantisation at the joint; then random, non-optimised excitations (one per seed, 60 s) with
   current or torque noise, and closed-loop runs by the simulated cell's drives (issue 17; at
   most 30 seeds each). Then the normal filtering and decimation path. Every estimator of
   :mod:`drivegain.identify.compare` runs on the same prepared data; per gain: bias, spread,
   coverage of the reported 2σ, mean of z; payload errors and coverage; runtime; and issue
   17's "Must show" targets, pass or fail.
2. The paper's tables (2, 3, 4, 5) and Fig. 3 from our whole ``identify`` pipeline on MCAP logs
   of one seed, with the simulation truth beside them.
3. The real TX-40 recording (../shared/data/tx40-real), Case 1, beside FIGAROH's published
   values, with both coupled-wrist friction forms (skipped with a message when absent).
4. docs/validation.md with every table and figure (docs/validation/*.png, results.json).

The Monte Carlo alternates scenarios seed by seed and stops starting new seeds when the
budget is spent, so the scenarios have the same number of seeds (the capped ones at most their
cap); the document says how many were run. The seeds run on one local process per CPU
(``--workers``) or on a Dask cluster (``--scheduler``, issue 21): the same numbers either way.
The study itself is the library :mod:`drivegain.validation`; this script only reads the
options.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from drivegain.errors import InputError
from drivegain.validation.scenarios import DEFAULT_BUDGET_S, DEFAULT_SEEDS, QUICK_SEEDS, RESERVE_S
from drivegain.validation.study import check_options, render_study, run_study

# The checkout's docs/ and the real recording beside it: the defaults of a developer's run.
REPO = Path(__file__).resolve().parents[1]
SHARED_REAL = REPO.parent / "shared" / "data" / "tx40-real"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the study with the command line's options; exit status 0, or 2 on bad options."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument(
        "--seeds",
        type=int,
        default=None,
        help=f"noise seeds per scenario (default {DEFAULT_SEEDS})",
    )
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_SEEDS} seeds")
    parser.add_argument(
        "--budget",
        type=float,
        default=DEFAULT_BUDGET_S,
        help="seconds for the whole study: no new seed starts after budget "
        f"minus {RESERVE_S:.0f} s (default {DEFAULT_BUDGET_S:.0f})",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=REPO / "docs",
        help="folder receiving validation.md and validation/ (default docs/)",
    )
    parser.add_argument(
        "--real", default=str(SHARED_REAL), help="folder of the real TX-40 recording, or 'none'"
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        help="address of a running Dask scheduler (tcp://HOST:PORT) to run the seeds on",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="local worker processes without --scheduler (default: one per CPU)",
    )
    parser.add_argument(
        "--from-results",
        type=Path,
        default=None,
        metavar="RESULTS_JSON",
        help="instead of running the study: write the page again from a run's results.json "
        "(must-show verdicts recomputed, numbers and figures kept)",
    )
    args = parser.parse_args(argv)
    cmd = "python benchmarks/validate.py" + (
        " " + " ".join(sys.argv[1:]) if argv is None and len(sys.argv) > 1 else ""
    )
    if args.from_results is not None:
        try:
            render_study(args.from_results, args.out, command=cmd)
        except InputError as exc:
            print(f"validate.py: error: {exc}", file=sys.stderr)
            return 2
        print(f"wrote {args.out / 'validation.md'} from {args.from_results}")
        return 0
    seeds = args.seeds if args.seeds is not None else (QUICK_SEEDS if args.quick else DEFAULT_SEEDS)
    workers = args.workers if args.workers is not None else _cpus()
    try:
        check_options(seeds, args.budget, args.scheduler, workers)
    except InputError as exc:
        parser.error(exc.message)  # exits with status 2, as for any bad option
    real = None if args.real == "none" else Path(args.real)
    try:
        run_study(
            seeds=seeds,
            budget_s=args.budget,
            out=args.out,
            real=real,
            command=cmd,
            scheduler=args.scheduler,
            workers=workers,
        )
    except InputError as exc:  # e.g. a scheduler that does not answer
        print(f"validate.py: error: {exc.message}", file=sys.stderr)
        return 2
    return 0


def _cpus() -> int:
    """CPUs this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


if __name__ == "__main__":
    raise SystemExit(main())
