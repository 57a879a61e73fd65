"""Command-line handlers of the acquire component: ``acquire``, ``daemon`` and ``demo``."""

from __future__ import annotations

import argparse
import logging
import sys

from drivegain.drivers.bus import BusOverrides
from drivegain.errors import DrivegainError, InputError

log = logging.getLogger(__name__)


def acquire(args: argparse.Namespace) -> int:
    """``drivegain acquire``: one session in the foreground with a progress display.

    Exit status 0 when the run finished or was stopped by SIGINT/SIGTERM (the log is finished
    and the stop recorded), 2 for bad input (nothing written), 1 for a fault (the drives were
    quick-stopped and the log ends with the fault).
    """
    from drivegain.acquire.config import load_acquisition_config
    from drivegain.acquire.foreground import run_foreground
    from drivegain.acquire.logs import quiet_libraries
    from drivegain.acquire.request import RunRequest
    from drivegain.acquire.session import RunState, operator_stop_error
    from drivegain.acquire.stop import StopRequest, stop_on_signals
    from drivegain.drivers.clock import Clock

    quiet_libraries(args.debug)
    cfg = load_acquisition_config(args.config, _overrides(args))
    request = RunRequest(
        trajectory=args.trajectory,
        out=args.out,
        label=args.label,
        payload=args.payload,
        can_trace=getattr(args, "can_trace", None),
    )
    stop = StopRequest()
    with stop_on_signals(stop, lambda name: log.warning("%s received: stopping the run", name)):
        try:
            result = run_foreground(cfg, request, stop=stop)
        except InputError:
            raise  # nothing was written
        except DrivegainError:
            part = args.out.with_name(args.out.name + ".part")
            if args.out.exists():
                print(f"drivegain: log finished with the fault: {args.out}", file=sys.stderr)
            elif part.exists():
                print(f"drivegain: partial log left at {part}", file=sys.stderr)
            raise
    if result.state is RunState.STOPPED:
        raise operator_stop_error(result)
    stats = result.stats
    if cfg.clock == Clock.LOCKSTEP:
        timing = f"lockstep at {stats.get('speed', '?')} x real time"
    else:
        timing = (
            f"SYNC jitter p99 {stats.get('sync_jitter_p99_us', '?')} µs, overruns "
            f"{stats.get('overruns', '?')}, late cycles {stats.get('late_cycles', '?')}"
        )
    print(f"{result.path}: {result.cycles} cycles, {timing}, late TPDOs {stats.get('late_tpdo')}")
    return 0


def daemon(args: argparse.Namespace) -> int:
    """``drivegain daemon``: the acquisition service on its control socket until SIGTERM."""
    from drivegain.acquire.config import load_acquisition_config
    from drivegain.acquire.daemon import Daemon
    from drivegain.acquire.logs import configure
    from drivegain.acquire.stop import stop_on_signals
    from drivegain.errors import ConfigError

    cfg = load_acquisition_config(args.config, _overrides(args))
    if cfg.daemon is None:
        raise ConfigError("a [daemon] table is needed to run the daemon", file=cfg.source)
    configure(cfg.daemon.log_format, debug=args.debug)
    service = Daemon(cfg)
    with stop_on_signals(service.shutdown):
        return service.serve()


def demo(args: argparse.Namespace) -> int:
    """``drivegain demo``: the whole pipeline on the simulated TX-40 (see :mod:`.demo`)."""
    from drivegain.acquire.demo import run_demo
    from drivegain.acquire.logs import quiet_libraries

    quiet_libraries(args.debug)
    run_demo(
        args.out,
        seed=args.seed,
        trajectory=getattr(args, "trajectory", None),
        bus_overrides=_overrides(args),
        robot=getattr(args, "robot", "tx40"),
        plots=not getattr(args, "no_plots", False),
    )
    return 0


def _overrides(args: argparse.Namespace) -> BusOverrides | None:
    """The command line's ``--interface/--channel/--bitrate``, if any was given."""
    from drivegain.cli import bus_overrides

    given = BusOverrides(**bus_overrides(args))
    return given if given.given else None
