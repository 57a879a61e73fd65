"""The acquisition TOML: ``[acquisition]``, ``[bus]``, optional ``[simulation]`` and ``[daemon]``.

Paths of configuration files (``robot``, the simulation truth) are relative to the TOML file;
runtime locations of the daemon (``socket``, ``output_dir``) are relative to the working directory.
The only difference between a simulated and a real cell is ``[bus]`` (``virtual`` vs ``socketcan``)
plus the ``[simulation]`` table: the acquisition code has no test branch.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivegain.acquire.supervision import Supervision
from drivegain.config._toml import Table, read_toml
from drivegain.config.robot import Robot, load_robot
from drivegain.drivers.bus import BusConfig, bus_config_from_table
from drivegain.drivers.ipcbus import INTERFACE as IPC_INTERFACE
from drivegain.drivers.sim import SimConfig, sim_config_from_table

#: Buses a simulated cell may be attached to.
SIMULATION_INTERFACES = ("virtual", IPC_INTERFACE)

_ACQ_KEYS = {
    "robot",
    "period_s",
    "eds",
    "following_error",
    "position_margin",
    "velocity_margin",
    "flush_interval_s",
    "queue_s",
    "settle_s",
    "bus_load_warn",
    "max_overruns",
    "rt_priority",
    "tpdo_timeout_s",
}
_DAEMON_KEYS = {"socket", "output_dir", "log_format", "idle_check_s", "watchdog_s"}


@dataclass(frozen=True)
class DaemonSettings:
    """``[daemon]``: control socket, where runs are written, log style, idle check period (s)."""

    socket: Path
    output_dir: Path
    log_format: str = "json"
    idle_check_s: float = 0.1
    watchdog_s: float | None = None


@dataclass(frozen=True)
class AcquisitionConfig:
    """A validated acquisition TOML.

    ``period_s`` is the SYNC period (s); ``queue_s`` the seconds of cycles the recorder may hold
    in memory; ``settle_s`` the time the final setpoint is held before disabling;
    ``bus_load_warn`` the bus load fraction above which a run is allowed with a warning;
    ``tpdo_timeout_s`` how long after a SYNC a TPDO missing is a fault (TPDOs later than one
    period but within it are counted as late).
    """

    source: Path
    robot_path: Path
    robot: Robot
    period_s: float
    bus: BusConfig
    simulation: SimConfig | None
    supervision: Supervision
    daemon: DaemonSettings | None
    eds: Path | None = None
    flush_interval_s: float = 1.0
    queue_s: float = 10.0
    settle_s: float = 0.2
    bus_load_warn: float = 0.7
    rt_priority: int = 0
    tpdo_timeout_s: float = 0.02

    @property
    def clock(self) -> str:
        """``lockstep`` or ``realtime``: hardware is always realtime."""
        return self.simulation.clock if self.simulation is not None else "realtime"

    @property
    def queue_capacity(self) -> int:
        """Recorder queue length in records (cycles + events)."""
        return max(64, int(self.queue_s / self.period_s))


def load_acquisition_config(path: str | Path) -> AcquisitionConfig:
    """Load and validate an acquisition TOML.

    Raises
    ------
    ConfigError
        One line naming the file and the key at fault.
    """
    p = Path(path)
    root = Table(read_toml(p), p)
    root.reject_unknown({"acquisition", "bus", "simulation", "daemon"})
    a = root.table("acquisition")
    a.reject_unknown(_ACQ_KEYS)
    base = p.resolve().parent
    robot_path = _existing(a, "robot", base)
    robot = load_robot(robot_path)
    period = a.get_float("period_s", 0.004, positive=True)
    if not 1e-4 <= period <= 0.1:
        raise a.error("period_s", f"must be between 0.0001 and 0.1 s, got {period}")
    eds = _existing(a, "eds", base) if a.has("eds") else None
    supervision = _supervision(a, robot)
    bus = bus_config_from_table(root.table("bus"))
    sim = sim_config_from_table(root.table("simulation"), base) if root.has("simulation") else None
    if sim is not None and bus.interface not in SIMULATION_INTERFACES:
        raise root.table("bus").error(
            "interface",
            f"a [simulation] runs on the virtual bus (drives in this process) or {IPC_INTERFACE} "
            f"(drives in a child process), not {bus.interface}: simulated drives never go on a "
            "real bus",
        )
    daemon = _daemon(root.table("daemon")) if root.has("daemon") else None
    warn = a.get_float("bus_load_warn", 0.7, positive=True)
    if warn > 1.0:
        raise a.error("bus_load_warn", f"must be a fraction <= 1, got {warn}")
    sim_clock = sim.clock if sim is not None else "realtime"
    # lockstep: the simulator takes the time it takes on a busy machine; realtime: a drive
    # silent for several periods is lost
    tpdo_default = 2.0 if sim_clock == "lockstep" else max(5 * period, 0.01)
    tpdo_timeout = a.get_float("tpdo_timeout_s", tpdo_default, positive=True)
    if sim_clock == "realtime" and tpdo_timeout < period:
        raise a.error(
            "tpdo_timeout_s", f"must be at least one period ({period} s), got {tpdo_timeout}"
        )
    prio = a.get_int("rt_priority", 0, minimum=0)
    if prio > 99:
        raise a.error("rt_priority", f"SCHED_FIFO priority must be 0..99, got {prio}")
    return AcquisitionConfig(
        source=p,
        robot_path=robot_path,
        robot=robot,
        period_s=period,
        bus=bus,
        simulation=sim,
        supervision=supervision,
        daemon=daemon,
        eds=eds,
        flush_interval_s=a.get_float("flush_interval_s", 1.0, positive=True),
        queue_s=a.get_float("queue_s", 10.0, positive=True),
        settle_s=_nonnegative(a, "settle_s", 0.2),
        bus_load_warn=warn,
        rt_priority=prio,
        tpdo_timeout_s=tpdo_timeout,
    )


def _existing(t: Table, key: str, base: Path) -> Path:
    path = Path(t.get_str(key))
    path = path if path.is_absolute() else base / path
    if not path.is_file():
        raise t.error(key, f"file not found: {path}")
    return path


def _nonnegative(t: Table, key: str, default: float) -> float:
    v = t.get_float(key, default)
    if v < 0:
        raise t.error(key, f"must be >= 0, got {v}")
    return v


def _supervision(a: Table, robot: Robot) -> Supervision:
    if not a.has("following_error"):
        fe = np.full(robot.n, 0.05)
    elif isinstance(a.raw("following_error"), list):
        fe = a.get_floats("following_error", length=robot.n)
    else:
        fe = np.full(robot.n, a.get_float("following_error"))
    if np.any(fe <= 0):
        raise a.error("following_error", f"must be > 0 rad, got {fe.tolist()}")
    margin = a.get_float("velocity_margin", 1.25, positive=True)
    if margin < 1.0:
        raise a.error("velocity_margin", f"must be >= 1 (a factor of the limit), got {margin}")
    return Supervision(
        following_error=fe,
        position_margin=_nonnegative(a, "position_margin", 0.02),
        velocity_margin=margin,
        max_overruns=a.get_int("max_overruns", 3, minimum=1),
    )


def _daemon(d: Table) -> DaemonSettings:
    d.reject_unknown(_DAEMON_KEYS)
    watchdog = d.get_float("watchdog_s", positive=True) if d.has("watchdog_s") else None
    return DaemonSettings(
        socket=Path(d.get_str("socket")),
        output_dir=Path(d.get_str("output_dir")),
        log_format=d.get_str("log_format", "json", choices=("json", "text")),
        idle_check_s=d.get_float("idle_check_s", 0.1, positive=True),
        watchdog_s=watchdog,
    )
