"""``drivegain demo``: the whole pipeline on a simulated robot (TX-40, or ``--robot ur5``), no
hardware.

1. The excitation: the shipped optimised trajectory (``config/tx40-excitation.json``), else one
   optimised now.
2. Run a (unloaded) and run b (the calibrated 4.59 kg payload) acquired over the mocked CAN bus
   (python-can ``virtual``) against the simulated drives in ``lockstep``, with the realistic
   simulator settings of ``config/acquire-sim.toml`` (true gains of the paper, encoder
   quantisation, 0.05 N·m-equivalent current noise).
3. ``identify`` on both logs (the default gain estimator), then a table of a priori /
   identified / true gains.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table as RichTable

from drivegain.acquire.config import AcquisitionConfig, load_acquisition_config
from drivegain.acquire.foreground import run_foreground
from drivegain.acquire.rig import simulation_for_run
from drivegain.acquire.session import RunRequest, RunResult, RunState, operator_stop_error
from drivegain.acquire.stop import StopRequest, stop_on_signals
from drivegain.config import load_truth, resource_path
from drivegain.config.excitation import (
    DEFAULT_BASE_FREQUENCY_HZ,
    DEFAULT_HARMONICS,
    DEFAULT_PERIODS,
)
from drivegain.console import make_console
from drivegain.drivers.bus import BusOverrides
from drivegain.errors import ConfigError, IdentificationError
from drivegain.fileio import write_atomic

log = logging.getLogger(__name__)

SIM_CONFIG = "acquire-sim.toml"
SHIPPED_TRAJECTORY = "tx40-excitation.json"
PAYLOAD = "payloads/calibrated-4590g.toml"
#: Age of the simulated drives' current samples (samples): they report the current reference
#: averaged over the SYNC period that ends at the position sample (``drivegain identify
#: --current-delay``).
SIM_CURRENT_DELAY = 0.5
#: ``--robot``: shipped robot name -> (simulated acquisition TOML, shipped trajectory).
ROBOTS = {
    "tx40": (SIM_CONFIG, SHIPPED_TRAJECTORY),
    "ur5": ("acquire-sim-ur5.toml", "ur5-excitation.json"),
}


@dataclass(frozen=True)
class DemoResult:
    """What the demo produced: logs, report folder, the three sets of gains (N·m/A)."""

    trajectory: Path
    unloaded: Path
    loaded: Path
    report_dir: Path
    apriori: np.ndarray
    identified: np.ndarray
    identified_std: np.ndarray
    true: np.ndarray

    @property
    def relative_error(self) -> np.ndarray:
        """(identified − true) / true per joint."""
        return (self.identified - self.true) / self.true


def demo_trajectory(
    out: Path,
    robot_path: Path,
    console: Console,
    shipped: str = SHIPPED_TRAJECTORY,
    nominal: Path | None = None,
) -> Path:
    """The shipped trajectory, or one optimised into ``out`` when none is shipped
    (``nominal``: the dynamic parameters the optimiser assumes, for a robot without a shipped
    model)."""
    try:
        return resource_path(shipped)
    except FileNotFoundError:
        pass
    target = out / shipped
    if target.is_file():
        return target
    from drivegain.excite.commands import excite

    console.print("no shipped trajectory: optimising one (about a minute)...")
    args = argparse.Namespace(
        robot=robot_path,
        out=target,
        payload=resource_path(PAYLOAD),
        seed=0,
        budget=60.0,
        harmonics=DEFAULT_HARMONICS,
        base_frequency=DEFAULT_BASE_FREQUENCY_HZ,
        periods=DEFAULT_PERIODS,
        criterion="cond",
        plot=None,
        debug=False,
        nominal=nominal,
    )
    excite(args)
    return target


def run_demo(
    out: Path,
    *,
    seed: int = 1,
    trajectory: Path | None = None,
    config: Path | None = None,
    console: Console | None = None,
    progress: bool | None = None,
    bus_overrides: BusOverrides | None = None,
    robot: str = "tx40",
    plots: bool = True,
) -> DemoResult:
    """Run the demo into ``out`` and print the gains.

    Parameters
    ----------
    out
        Output folder (created); the demo's own files in it are replaced.
    seed
        Seed of the simulated noise of run a (run b uses ``seed + 1``).
    trajectory
        Use this trajectory instead of the shipped one.
    config
        Use this acquisition TOML instead of the shipped ``acquire-sim.toml`` (must simulate).
    console
        Where to print (stdout by default).
    progress
        Progress bars (default: when stderr is a terminal).
    bus_overrides
        ``--interface/--channel/--bitrate``: e.g. the simulated drives on ``socketcan`` /
        ``vcan0`` (never a real device: the configuration refuses it).
    robot
        ``--robot``: a shipped robot of :data:`ROBOTS` (``tx40``, ``ur5``).
    plots
        False (``--no-plots``): the identification renders no figure.
    """
    # stdout, not wrapped at a guessed 80 columns when piped (drivegain.console)
    console = console or make_console()
    if robot not in ROBOTS:
        raise ConfigError(f"unknown demo robot {robot!r} (one of {', '.join(ROBOTS)})")
    sim_config, shipped = ROBOTS[robot]
    cfg = load_acquisition_config(config or resource_path(sim_config), bus_overrides)
    if cfg.simulation is None:
        raise ConfigError("the demo needs a [simulation] table", file=cfg.source)
    out.mkdir(parents=True, exist_ok=True)
    nominal = None if robot == "tx40" else cfg.simulation.truth
    traj = trajectory or demo_trajectory(out, cfg.robot_path, console, shipped, nominal)
    payload = resource_path(PAYLOAD)
    console.print(
        f"[bold]drivegain demo[/bold]: simulated {cfg.robot.name}, {cfg.robot.n} drives on "
        f"the mocked CAN bus ({cfg.bus.interface}:{cfg.bus.channel}), {cfg.clock}, "
        f"{1 / cfg.period_s:g} Hz; trajectory {traj}"
    )
    plan = [
        ("unloaded", None, out / "run-a-unloaded.mcap", seed),
        ("loaded", payload, out / "run-b-loaded.mcap", seed + 1),
    ]
    results: list[RunResult] = []
    stop = StopRequest()
    with stop_on_signals(stop):
        for label, pl, path, run_seed in plan:
            for old in (path, path.with_name(path.name + ".part")):
                old.unlink(missing_ok=True)
            sim = simulation_for_run(cfg.simulation, pl, run_seed)
            res = run_foreground(
                cfg,
                RunRequest(trajectory=traj, out=path, label=label, payload=pl),
                stop=stop,
                simulation=sim,
                progress=progress,
                title=f"run {'a' if pl is None else 'b'} ({label})",
            )
            if res.state is RunState.STOPPED:
                raise operator_stop_error(res)
            results.append(res)
            console.print(
                f"  {label:<9} {res.cycles} cycles -> {res.path} "
                f"(max following error {max(res.max_following_error):.2e} rad)"
            )
    report_dir = out / "identification"
    identified, std = _identify(
        cfg, results[0], results[1], payload, report_dir, progress, plots=plots
    )
    truth = load_truth(cfg.simulation.truth)
    result = DemoResult(
        trajectory=traj,
        unloaded=results[0].path or plan[0][2],
        loaded=results[1].path or plan[1][2],
        report_dir=report_dir,
        apriori=cfg.robot.apriori_gains,
        identified=identified,
        identified_std=std,
        true=np.asarray(truth.gains, dtype=float),
    )
    _report_truth(cfg, result)
    _print_table(console, cfg, result)
    return result


def truth_markdown(joint_names: list[str], r: DemoResult) -> str:
    """The report section that compares the identified gains with the simulator's truth."""
    rows = [
        "## Simulation truth (demo)",
        "",
        "The runs were simulated, so the true drive gains are known: the table compares them "
        "with the a priori and the identified ones (as the terminal does).",
        "",
        "| joint | a priori N·m/A | identified N·m/A | 2σ N·m/A | true N·m/A "
        "| a priori vs true % | identified vs true % |",
        "|---|---|---|---|---|---|---|",
    ]
    for j, name in enumerate(joint_names):
        rows.append(
            f"| {name} | {r.apriori[j]:.4g} | {r.identified[j]:.4g} | "
            f"{2 * r.identified_std[j]:.3g} | {r.true[j]:.4g} | "
            f"{100 * (r.apriori[j] / r.true[j] - 1):+.2f} | {100 * r.relative_error[j]:+.3f} |"
        )
    worst = float(np.max(np.abs(r.relative_error)))
    rows += ["", f"Largest error of the identified gains: {100 * worst:.3f} %.", ""]
    return "\n".join(rows)


def _report_truth(cfg: AcquisitionConfig, r: DemoResult) -> None:
    """Add the true gains and the errors to the identification's reports (each file replaced
    atomically): after the drive gain table in ``report.md`` and ``report.html``, as
    ``simulation_truth`` in ``report.json``."""
    from drivegain.identify.html import html_report

    folder = r.report_dir
    md = (folder / "report.md").read_text(encoding="utf-8")
    section = truth_markdown(cfg.robot.joint_names, r)
    start = md.find("\n## Drive gains")
    after = md.find("\n## ", start + 1) if start >= 0 else -1
    md = md + "\n" + section if after < 0 else md[: after + 1] + section + md[after:]
    doc = json.loads((folder / "report.json").read_text(encoding="utf-8"))
    doc["simulation_truth"] = {
        "gains": [float(g) for g in r.true],
        "identified_relative_error": [float(e) for e in r.relative_error],
        "apriori_relative_error": [
            float(a / t - 1) for a, t in zip(r.apriori, r.true, strict=True)
        ],
    }
    title = f"Drive gain identification: {cfg.robot.name} (simulated)"
    write_atomic(folder / "report.md", md.encode("utf-8"))
    write_atomic(folder / "report.html", html_report(md, folder, title).encode("utf-8"))
    write_atomic(folder / "report.json", (json.dumps(doc, indent=2) + "\n").encode("utf-8"))


def _identify(
    cfg: AcquisitionConfig,
    a: RunResult,
    b: RunResult,
    payload: Path,
    report_dir: Path,
    progress: bool | None,
    plots: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    from drivegain.identify.pipeline import IdentifyRequest, run_identify

    assert a.path is not None and b.path is not None
    outcome = run_identify(
        IdentifyRequest(
            robot=cfg.robot_path,
            unloaded=a.path,
            loaded=b.path,
            payload=payload,
            out=report_dir,
            current_delay=SIM_CURRENT_DELAY,
            progress=sys.stderr.isatty() if progress is None else progress,
            plots=plots,
        )
    )
    res = outcome.result
    for w in res.warnings:
        log.warning("identify: %s", w)
    if res.gains_std is None:
        raise IdentificationError("the identification did not identify the gains")
    return np.asarray(res.gains, dtype=float), np.asarray(res.gains_std, dtype=float)


def _print_table(console: Console, cfg: AcquisitionConfig, r: DemoResult) -> None:
    table = RichTable(title="Drive gains, N·m/A (joint side)")
    for col in ("joint", "a priori", "identified", "± 2σ", "true", "error vs true"):
        table.add_column(col, justify="right")
    for j, name in enumerate(cfg.robot.joint_names):
        table.add_row(
            name,
            f"{r.apriori[j]:.3f}",
            f"{r.identified[j]:.3f}",
            f"{2 * r.identified_std[j]:.3f}",
            f"{r.true[j]:.3f}",
            f"{100 * r.relative_error[j]:+.2f} %",
        )
    console.print(table)
    worst = float(np.max(np.abs(r.relative_error)))
    console.print(f"largest error of the identified gains: {100 * worst:.2f} %")
    console.print(f"logs: {r.unloaded}, {r.loaded}")
    console.print(f"report: {r.report_dir}")
