"""The study driver: Monte Carlo, the paper's tables, the real recording, figures, document.

:func:`run_study` is what ``benchmarks/validate.py`` runs; it writes ``out/validation.md`` and
``out/validation/`` (figures and ``results.json``, every number of the page).
:func:`render_study` writes the page again from a run's ``results.json`` without simulating
(``validate.py --from-results``).
"""

from __future__ import annotations

import json
import math
import os
import platform
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drivegain.errors import InputError
from drivegain.fileio import reading, write_atomic
from drivegain.identify.blas import limited_blas_threads
from drivegain.validation.cluster import check_scheduler, run_monte_carlo
from drivegain.validation.document import document_text, write_document
from drivegain.validation.figures import figure_coverage, figure_gain_errors, figure_payload
from drivegain.validation.mustshow import must_show
from drivegain.validation.paper import pipeline_tables
from drivegain.validation.real import real_tx40, skip_reason
from drivegain.validation.scenarios import (
    RATE_HZ,
    RESERVE_S,
    SCENARIOS,
    Scenario,
    scenario_level,
)
from drivegain.validation.statistics import decimated_noise_factor, scenario_summary
from drivegain.validation.world import make_world


def _json_default(o: Any) -> Any:
    """numpy scalars and arrays as JSON numbers and lists."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.floating | np.integer):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _cpus() -> int:
    """CPUs this process may run on (the affinity mask where the platform has one)."""
    return (
        len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    )


def check_options(
    seeds: int, budget_s: float, scheduler: str | None = None, workers: int = 1
) -> None:
    """Refuse a study that cannot produce statistics or cannot run.

    Raises
    ------
    InputError
        If ``seeds`` is below 2 (no spread), ``budget_s`` (s) is not a positive number,
        ``workers`` is below 1 or ``scheduler`` is not ``tcp://HOST:PORT``.
    """
    if seeds < 2:
        raise InputError("--seeds must be at least 2", key="seeds")
    if not (math.isfinite(budget_s) and budget_s > 0):
        raise InputError("--budget must be a positive number of seconds", key="budget")
    if workers < 1:
        raise InputError("--workers must be at least 1", key="workers")
    check_scheduler(scheduler)


def run_study(
    *,
    seeds: int,
    budget_s: float,
    out: Path,
    rate_hz: float = RATE_HZ,
    real: Path | None = None,
    command: str = "",
    scenarios: Sequence[Scenario] = SCENARIOS,
    progress: Callable[[str], None] = print,
    scheduler: str | None = None,
    workers: int = 1,
) -> dict[str, Any]:
    """The whole study; writes ``out/validation.md`` and ``out/validation/``.

    Parameters
    ----------
    seeds
        Noise seeds per scenario at most (≥ 2).
    budget_s
        Wall-clock budget, s: no new seed starts after ``budget_s`` minus
        :data:`~drivegain.validation.scenarios.RESERVE_S`.
    out
        Folder receiving ``validation.md`` and ``validation/``.
    rate_hz
        Sample rate of the simulated recordings, Hz.
    real
        Folder of the real TX-40 recording, or ``None`` to skip that section.
    command
        The command line quoted in the document.
    scenarios
        Noise levels, each one of :data:`~drivegain.validation.scenarios.SCENARIOS`.
    progress
        Receives one line of progress now and then.
    scheduler
        Address of a Dask scheduler (``tcp://HOST:PORT``) running the Monte Carlo's seeds, or
        ``None`` for this machine.
    workers
        Without ``scheduler``: local worker processes of the Monte Carlo (1: this process).

    Returns
    -------
    dict
        Everything written to ``results.json``.

    Raises
    ------
    InputError
        On too few seeds, a budget that is not positive, an unknown scenario, a bad worker
        count or scheduler address, or a scheduler that does not answer.
    """
    check_options(seeds, budget_s, scheduler, workers)
    for sc in scenarios:  # refuse an unknown scenario before the budget is spent, not after
        scenario_level(sc)
    t_start = time.perf_counter()
    deadline = t_start + max(0.0, budget_s - RESERVE_S)
    figures = out / "validation"
    figures.mkdir(parents=True, exist_ok=True)
    # One BLAS thread: OpenBLAS threads thrash on shared, busy cores and slow the study down.
    with limited_blas_threads(1), tempfile.TemporaryDirectory(prefix="validate-") as tmp:
        work = Path(tmp)
        world = make_world(rate_hz)
        progress(
            f"Monte Carlo: up to {seeds} seeds x {len(scenarios)} scenarios "
            f"(budget {budget_s:.0f} s)"
        )
        results = run_monte_carlo(
            world, seeds, deadline, scenarios, progress, scheduler=scheduler, workers=workers
        )
        factor = decimated_noise_factor(world)
        summary = {sc.key: scenario_summary(results[sc.key], world, factor) for sc in scenarios}
        progress("paper's tables through drivegain identify")
        tab = pipeline_tables(world, scenarios[0], 0, work, figures)
        real_data = None
        skipped = skip_reason(real)
        if real is not None and skipped is None:
            progress("real TX-40 recording")
            real_data = real_tx40(real, work)
        if skipped:
            progress(f"real TX-40: skipped: {skipped}")
        figure_gain_errors(summary, world.robot.joint_names, figures / "gain-errors.png")
        figure_coverage(summary, results, world, figures / "coverage.png")
        figure_payload(summary, scenarios[0].key, figures / "payload-errors.png")
        elapsed = time.perf_counter() - t_start
        data: dict[str, Any] = {
            "meta": {
                "command": command or "python benchmarks/validate.py",
                "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                "machine": f"{platform.machine()}, {_cpus()} CPUs, Python "
                f"{platform.python_version()}, numpy {np.__version__}",
                "seeds_requested": seeds,
                "seeds_run": max(len(v) for v in results.values()),
                "seeds_per_scenario": {k: len(v) for k, v in results.items()},
                "where": scheduler or f"{workers} local process(es)",
                "budget_s": budget_s,
                "elapsed_s": elapsed,
                "rate_hz": rate_hz,
            },
            "truth_gains": world.truth.gains.tolist(),
            "apriori_gains": world.robot.apriori_gains.tolist(),
            "monte_carlo": summary,
            "must_show": must_show(summary),
            "tables": tab,
            "real": real_data,
            "real_skipped": skipped,
            "noise_factor": factor,
        }
        (figures / "results.json").write_text(
            json.dumps(data, indent=1, default=_json_default) + "\n", encoding="utf-8"
        )
        write_document(out / "validation.md", figures, data, world)
    progress(f"wrote {out / 'validation.md'} and {figures}/ in {elapsed / 60:.1f} min")
    return data


def render_study(results: Path, out: Path, command: str = "") -> dict[str, Any]:
    """``out/validation.md`` written again from a study's ``results.json``, without simulating.

    The must-show verdicts are recomputed from the run's summary with this tree's targets
    (:func:`~drivegain.validation.mustshow.must_show`); every number stays the run's. The
    figures need the per-seed results, so they are not drawn again: the page links those in
    ``out/validation/``. ``out/validation/results.json`` gets the new verdicts and, in its
    ``meta``, when and by what the page was written again. Both files are replaced whole.

    Parameters
    ----------
    results
        A ``results.json`` written by :func:`run_study` (it may be the one in ``out``).
    out
        Folder receiving ``validation.md`` and ``validation/results.json``.
    command
        The command line quoted in the document.

    Returns
    -------
    dict
        What ``results.json`` now holds.

    Raises
    ------
    InputError
        When ``results`` cannot be read or is not a study's results.
    """
    with reading(results, expected="a results.json"):
        text = results.read_text(encoding="utf-8")
    try:
        data = json.loads(text)
        summary, meta = data["monte_carlo"], data["meta"]
        rate_hz = float(meta["rate_hz"])
        checks = must_show(summary)
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(
            f"not the results of a validation study ({type(exc).__name__}: {exc})", file=results
        ) from None
    data["must_show"] = checks
    meta["rendered"] = {
        "command": command or f"python benchmarks/validate.py --from-results {results}",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    figures = out / "validation"
    page = document_text(out / "validation.md", figures, data, make_world(rate_hz))
    write_atomic(
        figures / "results.json",
        (json.dumps(data, indent=1, default=_json_default) + "\n").encode(),
    )
    write_atomic(out / "validation.md", page.encode())
    return data
