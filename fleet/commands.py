"""``drivegain batch``: identify a fleet's runs on Dask, then the fleet table and drift report.

Options are declared in :mod:`drivegain.cli`; this module does the work.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from drivegain.fleet.campaign import load_batch
from drivegain.fleet.drift import write_fleet_outputs
from drivegain.fleet.engine import EngineOptions, quiet_dask, run_batch


def batch_command(args: argparse.Namespace) -> int:
    """Handler of ``drivegain batch``: 0 when every identification succeeded, 1 otherwise
    (the table and drift report are written either way, failures listed in them)."""
    batch = load_batch(
        str(args.source),
        out=args.out,
        robot=args.robot,
        payload=args.payload,
        threshold=args.threshold,
        baseline=args.baseline,
        retries=args.retries,
    )
    if args.no_identify_plots:
        tasks = [dataclasses.replace(t, identify_plots=False) for t in batch.tasks]
        batch = dataclasses.replace(batch, tasks=tasks)
    engine = EngineOptions(scheduler=args.scheduler, workers=args.workers, progress=True)
    with quiet_dask(getattr(args, "debug", False)):
        outcome = run_batch(batch, engine)
    opts = batch.options
    fleet = write_fleet_outputs(opts.out, opts.threshold, opts.baseline)
    rate = 60.0 * outcome.computed / outcome.seconds if outcome.computed else 0.0
    print(
        f"batch: {len(outcome.results)} identifications: {outcome.computed} run "
        f"({rate:.1f}/min on {outcome.workers} worker(s)), {outcome.skipped} already done, "
        f"{outcome.failed} failed"
    )
    drift = fleet.drift
    print(
        f"drift: {len(drift.rows)} comparisons against each robot's baseline, "
        f"{len(drift.flagged)} beyond ±{drift.threshold:g}σ"
    )
    for d in drift.flagged:
        pct = "" if d.change_percent is None else f" ({d.change_percent:+.3g} %)"
        print(
            f"  {d.robot_id} {d.parameter}: {d.baseline_value:.6g} -> {d.value:.6g}{pct}, "
            f"{d.z:+.3g}σ ({d.baseline} -> {d.campaign})"
        )
    for note in drift.notes:
        print(f"drivegain: warning: {note}", file=sys.stderr)
    print(f"wrote {opts.out}: fleet.parquet/.csv, drift.parquet/.csv/.json, drift/*.png")
    for r in outcome.results:
        if not r.ok:
            print(
                f"drivegain: error: {r.task['robot_id']} {r.task['campaign']}: {r.error}",
                file=sys.stderr,
            )
    return 0 if outcome.failed == 0 else 1
