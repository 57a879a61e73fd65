"""What each subcommand's ``--help`` says above and below its options: a description and one or
two examples that run as written with the files shipped with drivegain.

Paths under ``config/`` are the shipped files as they are in a source checkout (the installed
package holds the same files in ``drivegain/config``); ``drivegain-demo/`` is what
``drivegain demo`` writes, so the identification examples run right after the demo.
"""

from __future__ import annotations

import argparse
import textwrap

#: "command [action]" -> (description, examples)
DOCS: dict[str, tuple[str | None, list[str]]] = {
    "demo": (
        "The whole pipeline without hardware: an excitation, two runs (unloaded, then with the "
        "calibrated 4.59 kg payload) over the mocked CAN bus against simulated drives, then "
        "the gain identification. Prints a priori, identified and true gains; writes the logs "
        "and the report.",
        ["drivegain demo", "drivegain demo --robot ur5 --out ur5-demo --seed 3"],
    ),
    "excite": (
        "Optimise a periodic Fourier excitation within the robot's limits (condition number "
        "of the observation matrix, or log-determinant) and write it as trajectory JSON.",
        [
            "drivegain excite --robot tx40 --out traj.json --budget 30",
            "drivegain excite --robot tx40 --payload config/payloads/calibrated-4590g.toml "
            "--out traj.json",
        ],
    ),
    "acquire": (
        "Run one acquisition in the foreground: boot the drives, follow the trajectory, record "
        "every SYNC cycle to an MCAP log. Needs an acquisition TOML (bus, drives, robot), a "
        "trajectory and the log to write.",
        [
            "drivegain acquire --config config/acquire-sim.toml "
            "--trajectory config/tx40-excitation.json --out run-a.mcap",
            "drivegain acquire --config config/acquire-sim.toml "
            "--trajectory config/tx40-excitation.json --payload "
            "config/payloads/calibrated-4590g.toml --out run-b.mcap",
        ],
    ),
    "daemon": (
        "The long-running acquisition service: keeps the drives booted and takes run requests "
        "on a Unix socket (talk to it with 'drivegain ctl'). Prints where its socket is.",
        ["drivegain daemon --config config/acquire-sim.toml"],
    ),
    "ctl status": (
        "Ask a running daemon for its state, the run in progress and the last run.",
        ["drivegain ctl status --config config/acquire-sim.toml"],
    ),
    "ctl run": (
        "Ask a running daemon to start a run; its log goes to the daemon's output_dir.",
        [
            "drivegain ctl run --config config/acquire-sim.toml "
            "--trajectory config/tx40-excitation.json --wait"
        ],
    ),
    "ctl stop": (
        "Ask a running daemon to bring the run in progress to rest and finish its log.",
        ["drivegain ctl stop --config config/acquire-sim.toml"],
    ),
    "identify": (
        "Identify the drive gains (maximum likelihood by default, or the paper's IDIM-WTLS; "
        "from an unloaded and a loaded run) and the "
        "dynamic parameters (IDIM-WLS) from MCAP logs; writes report.json, report.md, "
        "report.html and the figures into --out.",
        [
            "drivegain identify --robot tx40 --unloaded drivegain-demo/run-a-unloaded.mcap "
            "--loaded drivegain-demo/run-b-loaded.mcap --out report",
            "drivegain identify --robot tx40 --unloaded drivegain-demo/run-a-unloaded.mcap "
            "--gains report/report.json --out report-gains-given",
        ],
    ),
    "convert": (
        "Import runs recorded by other programs into drivegain's MCAP log format.",
        ["drivegain convert csv --help", "drivegain convert table --help"],
    ),
    "convert csv": (
        "Two CSV files (positions, and currents or torques; one row per sample, one column "
        "per joint) at a fixed rate into an MCAP log.",
        [
            "drivegain convert csv --robot tx40 --positions q.csv --currents i.csv "
            "--rate 1000 --out run-a.mcap"
        ],
    ),
    # "convert table": its layout description and example are written where it is built
    "export": (
        "Write identified parameters in formats other tools load.",
        ["drivegain export urdf --help"],
    ),
    "export urdf": (
        "A URDF with the physically consistent inertial parameters of 'identify --consistent', "
        "and a controller TOML with the gains and friction.",
        [
            "drivegain export urdf --report report/report.json --robot tx40 "
            "--out tx40-identified.urdf"
        ],
    ),
    "batch": (
        "Identify many logs (a campaign TOML, or a folder or glob of logs) on a Dask cluster "
        "and flag gains that drifted from each robot's baseline.",
        [
            "drivegain batch 'cell-logs/*/*/*.mcap' --robot tx40 --out batch-results"
            "   # logs laid out ROBOT_ID/CAMPAIGN/*.mcap",
            "drivegain batch campaign.toml --workers 2",
        ],
    ),
    "model": (
        "Inspect the robot model.",
        ["drivegain model info --robot tx40"],
    ),
    "model info": (
        "Joints, dynamic parameters, the base parameters and their regrouping, and the "
        "condition number of the observation matrix at random states.",
        ["drivegain model info --robot tx40", "drivegain model info --robot ur5 --samples 1000"],
    ),
}


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def document(parser: argparse.ArgumentParser, prefix: str = "") -> None:
    """Give every subcommand of ``parser`` its description and examples (from :data:`DOCS`).

    A description already set where the parser was built is kept; examples are added below
    the options.
    """
    for name, sub in _subparsers(parser).items():
        key = f"{prefix} {name}".strip()
        description, examples = DOCS.get(key, (None, []))
        if description and not sub.description:
            sub.description = textwrap.fill(description, 88)
        if examples:
            lines = "\n".join(f"  {e}" for e in examples)
            sub.epilog = f"examples:\n{lines}"
        document(sub, key)
