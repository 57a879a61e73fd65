"""The ``drivegain`` command line (contracts §1).

Every subcommand's options are declared here; the work is done by a ``commands`` module of the
component that owns it, imported only when that subcommand runs (start-up stays fast and the
optional heavy imports stay out of ``--help``).

Exit status: 0 success, 2 bad input (one line on stderr naming the file, key or value), 1 any
other failure. No traceback unless ``--debug``.
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn

from drivegain import __version__
from drivegain.config import excitation as ex
from drivegain.config import resource_path
from drivegain.errors import DrivegainError, InputError, OperatorStop
from drivegain.fileio import check_output

Handler = Callable[[argparse.Namespace], int]

#: subcommand -> "module:function" that implements it
HANDLERS = {
    "model info": "drivegain.identify.commands:model_info",
    "demo": "drivegain.acquire.commands:demo",
    "excite": "drivegain.excite.commands:excite",
    "acquire": "drivegain.acquire.commands:acquire",
    "daemon": "drivegain.acquire.commands:daemon",
    "ctl": "drivegain.acquire.ctl:ctl_command",
    "identify": "drivegain.identify.pipeline:identify_command",
    "convert csv": "drivegain.identify.convert:convert_csv_command",
    "convert table": "drivegain.identify.table:convert_table_command",
    "export urdf": "drivegain.identify.export:export_urdf_command",
    "batch": "drivegain.fleet.commands:batch_command",
}


class _Help(argparse.RawDescriptionHelpFormatter):
    """Descriptions and examples as written; every option with a default says it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if "%(default)" in text or default is None or default is False or default == "==SUPPRESS==":
            return text
        return f"{text} (default: %(default)s)"


class _Parser(argparse.ArgumentParser):
    """argparse with the project's error format: one line naming the option, exit status 2."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", _Help)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"drivegain: error: {message} (see '{self.prog} --help')\n")


def _number(kind: type, lo: float | None, hi: float | None, unit: str = "") -> Callable[[str], Any]:
    """An argparse type: a finite ``kind`` within [lo, hi] (either end open when None)."""
    where = " ".join(
        part
        for part in (
            "" if lo is None else f">= {lo:g}",
            "and" if lo is not None and hi is not None else "",
            "" if hi is None else f"<= {hi:g}",
            unit,
        )
        if part
    )

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {kind.__name__}, got {text!r}") from None
        if (
            not math.isfinite(value)
            or (lo is not None and value < lo)
            or (hi is not None and value > hi)
        ):
            raise argparse.ArgumentTypeError(f"must be {where}, got {text}")
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


#: Bounds of the numeric options: generous for any real use, and small enough that a typo
#: cannot ask for an hour of work or more memory than the machine has.
SEED = _number(int, 0, 2**32 - 1)
SAMPLES = _number(int, 1, 1_000_000)
HARMONICS = _number(int, 1, 50)
PERIODS = _number(int, 1, 1000)
BASE_FREQUENCY = _number(float, 0.001, 10.0, "Hz")
BUDGET = _number(float, 0.1, 86_400.0, "s")
JOBS = _number(int, 1, 256)
MARGIN = _number(float, 0.0, math.pi, "rad")
FRACTION = _number(float, 1e-3, 1.0)
RATE = _number(float, 1.0, 100_000.0, "Hz")
POSITIVE = _number(float, 1e-9, 1e9)


def reversal_mask(text: str) -> float | str:
    """``--reversal-mask``: a taper in seconds, or ``auto`` (identify.maskgate.MASK_AUTO: the
    mask on the drives that stick, chosen by the fit)."""
    return text if text == "auto" else POSITIVE(text)


reversal_mask.__name__ = "taper"  # argparse names the type in its messages
DECIMATE = _number(int, 1, 10_000)
BITRATE = _number(int, 10_000, 1_000_000, "bit/s")
NONNEGATIVE = _number(float, 0.0, 1e9)
SAMPLE_FRACTION = _number(float, 0.0, 1.0)
SIGMAS = _number(float, 0.1, 1e6, "σ")
RETRIES = _number(int, 0, 100)


ROBOT_HELP = "robot TOML, or the name of a shipped robot (tx40)"


def robot_file(text: str) -> Path:
    """``--robot``: a path, or the name of a robot description shipped with drivegain."""
    path = Path(text)
    if path.exists() or path.suffix or "/" in text:
        return path
    try:
        return resource_path(f"{text}.toml")
    except FileNotFoundError:
        return path  # the loader names the missing file


class Terminated(BaseException):
    """SIGTERM reached a command outside an acquisition (which stops the robot itself): raised
    in the main thread so every ``finally`` and context manager runs, leaving no staging folder
    or temporary file behind."""


def _terminate(signum: int, frame: FrameType | None) -> None:
    raise Terminated


class NotAvailable(DrivegainError):
    """A subcommand whose implementation is not part of this build yet."""


def _handler(name: str) -> Handler:
    module_name, func = HANDLERS[name].split(":")
    try:
        module = importlib.import_module(module_name)
        handler: Handler = getattr(module, func)
    except ModuleNotFoundError as exc:
        if not (exc.name and module_name.startswith(exc.name)):
            raise  # a missing dependency, not a missing component
        raise NotAvailable(f"'drivegain {name}' is not yet available in this version") from None
    except AttributeError:
        raise NotAvailable(f"'drivegain {name}' is not yet available in this version") from None
    return handler


#: Output options checked before a command does any work (:func:`drivegain.fileio.check_output`):
#: subcommand -> (option attribute, check keywords). Recorded logs are never overwritten.
OUTPUTS: dict[str, list[tuple[str, dict[str, Any]]]] = {
    "demo": [("out", {"directory": True})],
    "excite": [("out", {"overwrite": True}), ("plot", {"overwrite": True, "key": "--plot"})],
    "identify": [("out", {"directory": True})],
    "convert csv": [("out", {"suffix": ".mcap"})],
    "convert table": [("out", {"suffix": ".mcap"})],
    "export urdf": [
        ("out", {"suffix": ".urdf", "overwrite": True}),
        ("controller", {"suffix": ".toml", "overwrite": True, "key": "--controller"}),
    ],
}


def _check_outputs(args: argparse.Namespace) -> None:
    for attr, kwargs in OUTPUTS.get(args.handler, []):
        value = getattr(args, attr, None)
        if value is not None:
            check_output(value, **kwargs)


def _bus_options(p: argparse.ArgumentParser) -> None:
    """``--interface/--channel/--bitrate`` over the acquisition TOML's bus, as python-can's own
    tools take them (see :func:`bus_overrides`)."""
    p.add_argument("--interface", help="python-can interface, over the TOML's [bus]")
    p.add_argument("--channel", help="CAN channel (can0, vcan0, ...), over the TOML's [bus]")
    p.add_argument("--bitrate", type=BITRATE, help="bitrate, bit/s, over the TOML's [bus]")


def bus_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The bus options given on the command line (keyword arguments of
    :class:`drivegain.drivers.bus.BusOverrides`)."""
    return {k: getattr(args, k, None) for k in ("interface", "channel", "bitrate")}


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``drivegain`` command."""
    common = _Parser(add_help=False)
    # SUPPRESS: a subcommand's parser must not reset a --debug given before the subcommand.
    common.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks"
    )
    parser = _Parser(
        prog="drivegain",
        description="Identify robot drive gains and dynamics (Gautier & Briot 2012) from "
        "CANopen runs.",
        parents=[common],
    )
    parser.add_argument("--version", action="version", version=f"drivegain {__version__}")
    sub = parser.add_subparsers(
        dest="command", metavar="COMMAND", required=True, parser_class=_Parser
    )

    p = sub.add_parser(
        "demo", parents=[common], help="whole pipeline on the simulated robot (no hardware)"
    )
    p.add_argument("--out", type=Path, default=Path("drivegain-demo"), help="output folder")
    p.add_argument("--seed", type=SEED, default=1, help="seed of the simulated noise")
    p.add_argument(
        "--robot",
        choices=("tx40", "ur5"),
        default="tx40",
        help="the simulated robot: the Staubli TX-40 (coupled wrist) or a UR5",
    )
    p.add_argument(
        "--no-plots", action="store_true", help="skip the identification's figures (faster)"
    )
    _bus_options(p)
    p.set_defaults(handler="demo")

    p = sub.add_parser("excite", parents=[common], help="optimise an excitation trajectory")
    p.add_argument("--robot", type=robot_file, required=True, help=ROBOT_HELP)
    p.add_argument("--out", type=Path, required=True, help="trajectory JSON to write")
    p.add_argument("--payload", type=Path, help="payload TOML (adds the WTLS criterion)")
    p.add_argument("--seed", type=SEED, default=0, help="random seed (same seed, same file)")
    p.add_argument("--budget", type=BUDGET, default=60.0, help="time budget, s")
    p.add_argument(
        "--harmonics", type=HARMONICS, default=ex.DEFAULT_HARMONICS, help="harmonics per joint"
    )
    p.add_argument(
        "--base-frequency",
        type=BASE_FREQUENCY,
        default=ex.DEFAULT_BASE_FREQUENCY_HZ,
        help="base frequency, Hz",
    )
    p.add_argument("--periods", type=PERIODS, default=ex.DEFAULT_PERIODS, help="periods to run")
    p.add_argument(
        "--criterion", choices=("cond", "logdet"), default="cond", help="optimality criterion"
    )
    p.add_argument(
        "--plot", type=Path, help="PNG of the joint trajectories (default: beside --out)"
    )
    p.add_argument(
        "--start", help="pose at rest the approach starts from, rad, 'q1,...,qn' (default: zeros)"
    )
    p.add_argument(
        "--nominal",
        type=Path,
        help="nominal dynamic parameters for the WTLS criterion (sim-truth TOML; default: the "
        "shipped model of a known robot)",
    )
    p.add_argument("--jobs", type=JOBS, help="worker processes (default: up to 2)")
    p.add_argument(
        "--position-margin", type=MARGIN, help="margin kept from each position limit, rad (0.1)"
    )
    p.add_argument(
        "--limit-fraction",
        type=FRACTION,
        help="fraction of the velocity/acceleration/jerk limits used (0.95)",
    )
    p.set_defaults(handler="excite")

    p = sub.add_parser("acquire", parents=[common], help="one acquisition session (foreground)")
    p.add_argument("--config", type=Path, required=True, help="acquisition TOML")
    p.add_argument("--trajectory", type=Path, required=True, help="trajectory JSON")
    p.add_argument("--out", type=Path, required=True, help="MCAP log to write")
    p.add_argument("--payload", type=Path, help="payload TOML fixed to the robot for this run")
    p.add_argument("--label", help="run label (default: unloaded/loaded)")
    p.add_argument(
        "--can-trace",
        type=Path,
        help="also record every CAN frame with python-can (.blf, .asc, .log by suffix)",
    )
    _bus_options(p)
    p.set_defaults(handler="acquire")

    p = sub.add_parser("daemon", parents=[common], help="the long-running acquisition service")
    p.add_argument("--config", type=Path, required=True, help="acquisition TOML")
    _bus_options(p)
    p.set_defaults(handler="daemon")

    p = sub.add_parser(
        "ctl",
        parents=[common],
        help="talk to a running daemon: status, run, stop",
        description="examples:\n    drivegain ctl status --config config/acquire-sim.toml\n"
        "    drivegain ctl run --socket drivegain-sim.sock --trajectory traj.json --wait\n"
        "    drivegain ctl stop --socket /run/drivegain/control.sock",
    )
    csub = p.add_subparsers(
        dest="ctl_action", metavar="ACTION", required=True, parser_class=_Parser
    )
    ctl = _Parser(add_help=False)
    ctl.add_argument("--socket", type=Path, help="the daemon's control socket")
    ctl.add_argument(
        "--config", type=Path, help="acquisition TOML whose [daemon] socket to use (no --socket)"
    )
    ctl.add_argument("--json", action="store_true", help="print the daemon's raw JSON reply")
    csub.add_parser("status", parents=[common, ctl], help="state, run in progress, last run")
    c = csub.add_parser("run", parents=[common, ctl], help="start a run (log in output_dir)")
    c.add_argument("--trajectory", type=Path, required=True, help="trajectory JSON")
    c.add_argument("--payload", type=Path, help="payload TOML fixed to the robot for this run")
    c.add_argument("--label", help="run label (default: unloaded/loaded)")
    c.add_argument("--wait", action="store_true", help="wait for the run to end, then summarise")
    csub.add_parser("stop", parents=[common, ctl], help="bring the run in progress to rest")
    p.set_defaults(handler="ctl")

    p = sub.add_parser("identify", parents=[common], help="offline identification from logs")
    p.add_argument("--robot", type=robot_file, required=True, help=ROBOT_HELP)
    p.add_argument("--unloaded", type=Path, required=True, help="run a (no payload), MCAP")
    p.add_argument("--loaded", type=Path, help="run b (with the payload), MCAP")
    p.add_argument(
        "--payload",
        type=Path,
        help="payload TOML of run b (default: the payload TOML attached to the --loaded log)",
    )
    p.add_argument(
        "--current",
        choices=("reference", "measured"),
        help="which current of the logs stands for the torque: the drives' current reference "
        "(default, the paper's v_τ) or the measured current",
    )
    p.add_argument(
        "--gains",
        help="fix the gains and skip their estimation: 'apriori' (the robot file's), "
        "'gear-ratios', a TOML with values = [...] (std = [...] optional), or a report.json; "
        "default: identify them when --loaded is given, else use the a priori gains",
    )
    p.add_argument("--validate", type=Path, help="a third run with a second payload (Table 5)")
    p.add_argument("--validate-payload", type=Path, help="payload TOML of the --validate run")
    p.add_argument("--friction", choices=("physical", "paper"), help="coupled-wrist friction form")
    p.add_argument(
        "--estimator",
        choices=("ml", "paper"),
        default="ml",
        help="gain estimator: 'ml', maximum likelihood in current units with a noise model "
        "estimated from the data and standard deviations from the errors' autocovariance, or "
        "'paper', the paper's "
        "IDIM-WTLS with the column weight α searched on a grid",
    )
    p.add_argument(
        "--alpha", type=POSITIVE, help="fix the V column weight instead of searching (paper only)"
    )
    p.add_argument(
        "--bootstrap",
        type=int,
        metavar="N",
        help="also report the gains' σ from N replicates (at least 10) of a residual block "
        "bootstrap of the maximum-likelihood fit, beside the reported σ (ml only; each "
        "replicate costs about one fit)",
    )
    p.add_argument("--cutoff", type=POSITIVE, help="low-pass cut-off of positions, Hz")
    p.add_argument(
        "--sign-cutoff",
        type=POSITIVE,
        metavar="HZ",
        help="low-pass cut-off of the velocity whose sign the Coulomb friction columns take, "
        "Hz (default: 8 times the position cut-off, at most 0.4 times the sample rate, lower "
        "where the encoder is coarse, or the position cut-off where that explains runs a and "
        "b's currents better): the position filter blurs the stop of a closed-loop drive at "
        "each reversal (docs/model.md)",
    )
    p.add_argument(
        "--reversal-mask",
        type=reversal_mask,
        metavar="S|auto",
        help="weight the equations near each velocity reversal out of every fit, before the "
        "decimation, rising back over S seconds either side (0.05-0.1 for drives in closed "
        "loop, which stick at reversals); auto: only on the drives whose fit says they stick "
        "(κ̂ ≥ 1), taper 0.1 s (default: every equation counts, docs/model.md)",
    )
    p.add_argument("--decimate", type=DECIMATE, help="decimation factor")
    p.add_argument(
        "--current-delay",
        type=SAMPLE_FRACTION,
        metavar="SAMPLES",
        help="age of each current sample relative to its position sample (0-1; 0.5 for drives "
        "that report the current averaged over the period ending at the sample, as the "
        "simulated drives do)",
    )
    p.add_argument(
        "--reference",
        type=Path,
        help="published base parameters to compare with (CSV: expression, value, %%σ, ...)",
    )
    p.add_argument(
        "--consistent",
        action="store_true",
        help="also fit the base parameters over physically consistent bodies (SDP, docs/model.md)",
    )
    p.add_argument(
        "--prior",
        type=Path,
        help="a priori parameters for --consistent (sim-truth TOML; default: shipped model)",
    )
    p.add_argument(
        "--prior-weight", type=NONNEGATIVE, help="weight of the pull towards --prior (1e-6)"
    )
    p.add_argument(
        "--consistent-gains",
        choices=("fixed", "apriori-sign", "positive"),
        help="--consistent: keep the gains (default) or solve them with a sign constraint",
    )
    p.add_argument(
        "--no-plots",
        action="store_true",
        help="skip the figures (faster; the report says they were not rendered)",
    )
    p.add_argument("--out", type=Path, required=True, help="report folder")
    p.set_defaults(handler="identify")

    p = sub.add_parser("convert", parents=[common], help="import data recorded elsewhere")
    conv = p.add_subparsers(dest="format", metavar="FORMAT", required=True, parser_class=_Parser)
    c = conv.add_parser("csv", parents=[common], help="CSV positions + currents -> MCAP")
    c.add_argument("--positions", type=Path, required=True, help="CSV of positions, rad")
    c.add_argument("--currents", type=Path, required=True, help="CSV of currents (A) or torques")
    c.add_argument("--rate", type=RATE, required=True, help="sample rate, Hz")
    c.add_argument("--motor-side", action="store_true", help="positions/currents are motor-side")
    c.add_argument(
        "--torque",
        action="store_true",
        help="the current file holds motor torques (N·m) rather than current references (A)",
    )
    c.add_argument("--robot", type=robot_file, required=True, help=ROBOT_HELP)
    c.add_argument("--run", default="unloaded", help="run label")
    c.add_argument("--payload", type=Path, help="payload TOML fixed to the robot during the run")
    c.add_argument("--out", type=Path, required=True, help="MCAP log to write")
    c.set_defaults(handler="convert csv")
    c = conv.add_parser(
        "table",
        parents=[common],
        help="one CSV or Parquet table with a time column -> MCAP",
        description="Expected layout (one row per sample, a header row naming the columns):\n"
        "\n    time,q1,...,q6,iref1,...,iref6,i1,...,i6\n    0.000,0.10,...\n    0.010,0.11,...\n"
        "\nexample:\n    drivegain convert table --input run.csv --time time --position 'q{}' "
        "--current-reference 'iref{}' --current 'i{}' --robot tx40 --run unloaded --out a.mcap\n"
        "\nColumn lists: comma-separated names or 1-based column numbers, or one name with {} "
        "for the joint number 1..n. The log keeps the real time stamps.",
        formatter_class=_Help,  # layout as written, defaults shown
    )
    c.add_argument("--input", type=Path, required=True, help="CSV, or Parquet (.parquet)")
    c.add_argument("--time", required=True, help="time column (name or number)")
    c.add_argument(
        "--time-unit", default="s", choices=("s", "ms", "us", "ns"), help="unit of the time column"
    )
    c.add_argument("--position", required=True, help="position columns, rad")
    c.add_argument("--current-reference", required=True, help="current reference columns, A")
    c.add_argument("--current", help="measured current columns, A")
    c.add_argument("--setpoint", help="commanded position columns, rad")
    c.add_argument("--rows", help="FIRST:LAST data rows kept, 1-based (either may be empty)")
    c.add_argument("--start", type=float, help="keep rows from this time, s after the first row")
    c.add_argument("--end", type=float, help="keep rows up to this time, s after the first row")
    c.add_argument("--motor-side", action="store_true", help="positions are motor angles")
    c.add_argument("--robot", type=robot_file, required=True, help=ROBOT_HELP)
    c.add_argument("--run", default="unloaded", help="run label (unloaded, loaded, ...)")
    c.add_argument("--payload", type=Path, help="payload TOML fixed to the robot during the run")
    c.add_argument("--out", type=Path, required=True, help="MCAP log to write (never replaced)")
    c.set_defaults(handler="convert table")

    p = sub.add_parser("export", parents=[common], help="identified parameters to other formats")
    esub = p.add_subparsers(dest="format", metavar="FORMAT", required=True, parser_class=_Parser)
    e = esub.add_parser("urdf", parents=[common], help="URDF + controller TOML from a report")
    e.add_argument(
        "--report", type=Path, required=True, help="report.json of identify --consistent"
    )
    e.add_argument("--robot", type=robot_file, required=True, help=ROBOT_HELP)
    e.add_argument("--out", type=Path, required=True, help="URDF to write")
    e.add_argument("--controller", type=Path, help="gains/friction TOML (default: beside --out)")
    e.set_defaults(handler="export urdf")

    p = sub.add_parser(
        "batch", parents=[common], help="identify a fleet's runs on Dask, fleet table and drift"
    )
    p.add_argument(
        "source",
        help="campaign TOML, or a folder or glob of logs laid out ROBOT_ID/CAMPAIGN/*.mcap "
        "(local paths or fsspec URLs)",
    )
    p.add_argument(
        "--out", help="results folder or fsspec URL (default: the campaign's [batch] out)"
    )
    p.add_argument(
        "--scheduler",
        help="address of a running Dask scheduler, tcp://HOST:PORT (default: a local cluster)",
    )
    p.add_argument("--workers", type=JOBS, help="local cluster workers (default: cores)")
    p.add_argument("--threshold", type=SIGMAS, help="drift flag beyond this many σ (5)")
    p.add_argument("--baseline", help="baseline campaign (default: each robot's earliest)")
    p.add_argument("--retries", type=RETRIES, help="retries of a failed task (2)")
    p.add_argument("--robot", help="logs folder: robot TOML or shipped name, when no robot.toml")
    p.add_argument("--payload", help="logs folder: payload TOML, when no payload.toml")
    p.add_argument(
        "--no-identify-plots",
        action="store_true",
        help="skip each identification's PNG plots (most of its time on short runs)",
    )
    p.set_defaults(handler="batch")

    p = sub.add_parser("model", parents=[common], help="inspect the robot model")
    msub = p.add_subparsers(
        dest="model_command", metavar="ACTION", required=True, parser_class=_Parser
    )
    m = msub.add_parser("info", parents=[common], help="joints, parameters, base parameters")
    m.add_argument("--robot", type=robot_file, required=True, help=ROBOT_HELP)
    m.add_argument("--samples", type=SAMPLES, default=300, help="random states for cond(W)")
    m.add_argument("--seed", type=SEED, default=0, help="seed of the random states")
    m.set_defaults(handler="model info")
    from drivegain.cli_help import document

    document(parser)  # every subcommand's description and examples (core/cli_help.py)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a bad option (already reported)
        return exc.code if isinstance(exc.code, int) else 2
    args.debug = getattr(args, "debug", False)
    from drivegain.console import install_logging

    # through the progress display's console on a terminal (core/console.py)
    install_logging(debug=args.debug)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if main_thread else None
    try:
        _check_outputs(args)
        return int(_handler(args.handler)(args))
    except InputError as exc:
        if args.debug:
            traceback.print_exc()
        print(f"drivegain: error: {exc}", file=sys.stderr)
        return 2
    except OperatorStop as exc:
        print(f"drivegain: stopped: {exc}", file=sys.stderr)
        return 0
    except DrivegainError as exc:
        if args.debug:
            traceback.print_exc()
        print(f"drivegain: error: {exc}", file=sys.stderr)
        return 1
    except MemoryError:
        print("drivegain: error: out of memory (try a smaller problem)", file=sys.stderr)
        return 1
    except BrokenPipeError:  # the reader went away (`| head`): nothing more to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # the file system, not a bug: say which file and why, in one line
        if args.debug:
            traceback.print_exc()
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"drivegain: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("drivegain: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        print("drivegain: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    except Exception as exc:  # a bug: one line for users, the traceback with --debug
        if args.debug:
            traceback.print_exc()
        print(
            f"drivegain: internal error: {type(exc).__name__}: {exc} (run with --debug)",
            file=sys.stderr,
        )
        return 1
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    raise SystemExit(main())
