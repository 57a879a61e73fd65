"""``drivegain excite``: optimise an excitation trajectory and write TRAJ.json and a PNG."""

from __future__ import annotations

import argparse
import logging
import os
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from drivegain.config import load_payload, load_robot, load_truth, resource_path
from drivegain.config.excitation import (
    DEFAULT_BASE_FREQUENCY_HZ,
    DEFAULT_HARMONICS,
    DEFAULT_PERIODS,
)
from drivegain.config.payload import Payload
from drivegain.config.robot import Robot
from drivegain.dynamics.params import truth_vector
from drivegain.errors import ConfigError, InputError, TrajectoryError
from drivegain.excite.criteria import Criterion
from drivegain.excite.evaluate import evaluate_metrics
from drivegain.excite.limits import ExcitationLimits
from drivegain.excite.motion import Motion, check_motion, plan_motion
from drivegain.excite.optimise import (
    ExcitationSettings,
    OptimisationResult,
    StartResult,
    optimise,
    plan_budget,
)
from drivegain.excite.plot import render_motion_png
from drivegain.excite.trajectory import save_trajectory, trajectory_document
from drivegain.fileio import write_atomic

log = logging.getLogger(__name__)

#: Nominal dynamic parameters shipped for robots we know (sim-truth format).
_NOMINAL = {"Staubli TX-40": "sim/tx40-truth.toml"}


#: Hard wall-clock cap, in budgets: only a machine far slower than the reference reaches it.
WALL_CAP = 4.0


class ExciteInputError(InputError):
    """A request the excitation cannot satisfy (start pose, options)."""


def _opt(args: argparse.Namespace, name: str, default: Any) -> Any:
    # Callers such as the demo build the Namespace themselves and may omit newer options.
    value = getattr(args, name, None)
    return default if value is None else value


def _positive(value: float, key: str) -> None:
    if not (np.isfinite(value) and value > 0):
        raise ExciteInputError(f"must be > 0, got {value}", key=key)


def parse_pose(text: str, robot: Robot) -> np.ndarray:
    """A pose from ``"q1,q2,...,qn"`` (rad), inside the robot's position limits.

    Raises
    ------
    ExciteInputError
        Wrong count, not a number, not finite, or outside the limits (names ``--start``).
    """
    try:
        q = np.array([float(x) for x in text.replace(" ", "").split(",")])
    except ValueError:
        raise ExciteInputError(
            f"expected {robot.n} comma-separated angles in rad, got {text!r}", key="--start"
        ) from None
    if q.shape[0] != robot.n:
        raise ExciteInputError(f"expected {robot.n} angles, got {q.shape[0]}", key="--start")
    if not np.all(np.isfinite(q)):
        raise ExciteInputError(f"angles must be finite, got {text!r}", key="--start")
    out = (q < robot.lower) | (q > robot.upper)
    if np.any(out):
        j = int(np.argmax(out))
        raise ExciteInputError(
            f"{robot.joint_names[j]} = {q[j]:g} rad is outside the position limits "
            f"[{robot.lower[j]:.4g}, {robot.upper[j]:.4g}] rad",
            key="--start",
        )
    return q


def nominal_parameters(robot: Robot, path: Path | None) -> tuple[np.ndarray, str]:
    """Nominal standard parameters for the WTLS criterion, and where they came from."""
    if path is None:
        shipped = _NOMINAL.get(robot.name)
        if shipped is None:
            raise ExciteInputError(
                f"the WTLS criterion needs nominal dynamic parameters of {robot.name!r}: "
                "pass --nominal FILE (sim-truth TOML format)",
                key="--nominal",
            )
        path = resource_path(shipped)
    truth = load_truth(path, robot.n)
    return truth_vector(robot, truth), str(path)


def excite(args: argparse.Namespace) -> int:
    """Handler of ``drivegain excite`` (options in :mod:`drivegain.cli`)."""
    from drivegain.console import console as shared_console

    console = shared_console(stderr=True)  # shared with the log handler
    robot = load_robot(args.robot)
    payload: Payload | None = None
    if args.payload is not None:
        payload = load_payload(args.payload, robot.n)
    harmonics = int(_opt(args, "harmonics", DEFAULT_HARMONICS))
    if harmonics < 1:
        raise ExciteInputError(f"must be >= 1, got {harmonics}", key="--harmonics")
    base_hz = float(_opt(args, "base_frequency", DEFAULT_BASE_FREQUENCY_HZ))
    _positive(base_hz, "--base-frequency")
    periods = int(_opt(args, "periods", DEFAULT_PERIODS))
    if periods < 1:
        raise ExciteInputError(f"must be >= 1, got {periods}", key="--periods")
    budget = float(_opt(args, "budget", 60.0))
    _positive(budget, "--budget")
    jobs = int(_opt(args, "jobs", min(2, os.cpu_count() or 1)))
    if jobs < 1:
        raise ExciteInputError(f"must be >= 1, got {jobs}", key="--jobs")
    margin = float(_opt(args, "position_margin", 0.1))
    if not (np.isfinite(margin) and margin >= 0):
        raise ExciteInputError(f"must be >= 0 rad, got {margin}", key="--position-margin")
    fraction = float(_opt(args, "limit_fraction", 0.95))
    if not (0 < fraction <= 1):
        raise ExciteInputError(f"must be in (0, 1], got {fraction}", key="--limit-fraction")
    criterion = Criterion(_opt(args, "criterion", "cond"))
    out = Path(args.out)
    plot_path = Path(_opt(args, "plot", out.with_suffix(".png")))
    for key, path in (("--out", out), ("--plot", plot_path)):
        if path.is_dir():
            raise ExciteInputError(f"{path} is a folder, expected a file name", key=key)
    # Impossible limits fail here, before any work (ConfigError names the robot file and key).
    limits = ExcitationLimits.from_robot(robot, margin, fraction)
    start_text = _opt(args, "start", None)
    q_start = (
        parse_pose(start_text, robot)
        if start_text is not None
        else np.clip(np.zeros(robot.n), limits.lower, limits.upper)
    )
    chi = None
    nominal_src = None
    if payload is not None:
        chi, nominal_src = nominal_parameters(robot, _opt(args, "nominal", None))
    starts, max_iter = plan_budget(budget)
    seed = int(_opt(args, "seed", 0))
    settings = ExcitationSettings(
        base_frequency_hz=base_hz,
        harmonics=harmonics,
        periods=periods,
        criterion=criterion,
        payload=payload,
        chi_nominal=chi,
        position_margin=margin,
        fraction=fraction,
        seed=seed,
        starts=starts,
        max_iter=max_iter,
        wall_cap_s=WALL_CAP * budget,
        jobs=jobs,
    )
    console.print(
        f"excite: {robot.name}, {harmonics} harmonics at {base_hz:g} Hz, criterion {criterion}"
        + (f" + WTLS with {payload.name}" if payload else "")
        + f"; {starts} starts (seed {seed}) on {jobs} worker(s)"
    )
    result = _run_with_progress(robot, settings, console)
    fourier = result.fourier
    with _Phases(console) as phase:
        with phase("approach and retreat (ruckig)"):
            try:
                motion = plan_motion(robot, fourier, q_start, limits=limits)
            except TrajectoryError as exc:
                raise ExciteInputError(f"unreachable start pose: {exc}", key="--start") from None
        # The whole motion at 1 kHz against the robot's own limits: cannot fail unless we have
        # a bug.
        with phase("whole motion checked at 1 kHz"):
            check_motion(robot, motion)
        with phase("metrics over one period"):
            metrics = evaluate_metrics(
                robot, fourier, payload=payload, chi_nominal=chi, design=result.design
            )
        with phase(f"plot {plot_path.name}"):
            png = render_motion_png(
                robot,
                motion,
                limits,
                title=f"{robot.name}: cond {metrics['cond']:.3g}, seed {seed}",
            )
    metrics["random_median_cond"] = float(np.median(result.random_conds))
    metrics["random_starts"] = len(result.starts)
    doc = trajectory_document(
        fourier,
        robot,
        metrics,
        limits,
        extra={
            "optimisation": {
                "criterion": str(criterion),
                "payload": payload.name if payload else None,
                "nominal_parameters": Path(nominal_src).name if nominal_src else None,
                "wtls_weight": settings.wtls_weight if payload else 0.0,
                "seed": seed,
                "budget_s": budget,
                "starts": starts,
                "completed_starts": len(result.starts),
                "max_iter": max_iter,
            },
            "approach": {
                "from": [float(x) for x in q_start],
                "duration_s": _bounds(motion, "approach"),
            },
            "retreat": {
                "to": [float(x) for x in q_start],
                "duration_s": _bounds(motion, "retreat"),
            },
        },
    )
    save_trajectory(out, doc)
    write_atomic(plot_path, png)
    _summary(console, result, metrics, out, plot_path, motion)
    return 0


class _Phases:
    """One progress line per phase after the optimisation (each shows its elapsed time, so no
    phase of the command is silent)."""

    def __init__(self, console: Any) -> None:
        from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

        self.progress = Progress(
            SpinnerColumn(finished_text="[green]✓"),
            TextColumn("{task.description}"),
            TimeElapsedColumn(),
            console=console,
            transient=False,
        )

    def __enter__(self) -> Callable[[str], AbstractContextManager[None]]:
        self.progress.__enter__()
        return self._phase

    def __exit__(self, *exc: object) -> None:
        self.progress.__exit__(None, None, None)

    @contextmanager
    def _phase(self, description: str) -> Iterator[None]:
        task = self.progress.add_task(description, total=1)
        yield
        self.progress.update(task, completed=1)
        self.progress.stop_task(task)


def _bounds(motion: Motion, phase: str) -> float:
    for ph, (t0, t1) in motion.phase_bounds.items():
        if ph.value == phase:
            return float(t1 - t0)
    return 0.0


def _run_with_progress(
    robot: Robot, settings: ExcitationSettings, console: Any
) -> OptimisationResult:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("[bold]optimising"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[best]}"),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    ) as bar:
        task = bar.add_task("starts", total=settings.starts, best="")

        def progress(r: StartResult, best: StartResult) -> None:
            bar.update(
                task,
                advance=1,
                best=f"best cond {best.cond:.3g} (start {best.index}); this one {r.cond:.3g} "
                f"from random {r.initial_cond:.3g}",
            )

        result = optimise(robot, settings, progress)
    if result.skipped:
        console.print(
            f"[yellow]warning:[/] wall-clock cap reached, {result.skipped} start(s) skipped: "
            "the result may differ from a run on a faster machine"
        )
    return result


def _summary(
    console: Any,
    result: OptimisationResult,
    metrics: dict[str, Any],
    out: Path,
    plot_path: Path,
    motion: Motion,
) -> None:
    console.print(
        f"cond (unit-norm columns, one period): {metrics['cond']:.3g}; median of "
        f"{metrics['random_starts']} random feasible trajectories: "
        f"{metrics['random_median_cond']:.3g}; unscaled cond {metrics['cond_unscaled']:.3g}"
    )
    if "wtls_cond" in metrics:
        console.print(
            f"WTLS (unloaded + loaded, design data): s1/s(p-1) = {metrics['wtls_cond']:.3g}"
        )
    console.print(
        f"motion: approach {_bounds(motion, 'approach'):.2f} s, excitation "
        f"{_bounds(motion, 'excitation'):.1f} s, retreat {_bounds(motion, 'retreat'):.2f} s; "
        f"optimised in {result.seconds:.1f} s"
    )
    print(f"wrote {out} and {plot_path}")


__all__ = ["ConfigError", "ExciteInputError", "excite", "nominal_parameters", "parse_pose"]
