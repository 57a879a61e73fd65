"""The acquisition TOML: ``[acquisition]``, ``[bus]``, optional ``[simulation]`` and ``[daemon]``.

Paths of configuration files (``robot``, the simulation truth) are relative to the TOML file;
runtime locations of the daemon (``socket``, ``output_dir``) are relative to the working directory.
The raw CAN trace ``can_trace`` is relative to each run's log folder (see
:mod:`drivegain.acquire.cantrace`).
The only difference between a simulated and a real cell is ``[bus]`` (``virtual`` vs ``socketcan``)
plus the ``[simulation]`` table: the acquisition code has no test branch.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from enum import StrEnum
from pathlib import Path

import numpy as np

from drivegain.acquire.cantrace import trace_name_problem
from drivegain.acquire.supervision import Supervision
from drivegain.config._toml import Table, read_root
from drivegain.config.robot import Robot, load_robot
from drivegain.config.schema import PathRule, derived, keys_of, load_table, setting
from drivegain.drivers.bus import (
    BusConfig,
    BusOverrides,
    bus_config_from_python_can,
    bus_config_from_table,
    default_tpdo_timeout,
    with_overrides,
)
from drivegain.drivers.clock import Clock
from drivegain.drivers.heartbeat import (
    CONSUMER_PERIODS,
    DEFAULT_MASTER_HEARTBEAT_S,
    DEFAULT_MASTER_NODE_ID,
)
from drivegain.drivers.ipcbus import INTERFACE as IPC_INTERFACE
from drivegain.drivers.link import Timeouts
from drivegain.drivers.simconfig import SimConfig, check_fault_nodes, sim_config_from_table

#: Buses a simulated cell may be attached to.
SIMULATION_INTERFACES = ("virtual", IPC_INTERFACE)
#: Kernel CAN devices simulated drives may use: Linux's virtual CAN (``vcan0``...), which no real
#: drive is ever on. A real interface (``can0``) is never given to simulated drives.
SIMULATION_SOCKETCAN_PREFIX = "vcan"


def simulation_bus_allowed(interface: str, channel: str) -> bool:
    """Whether simulated drives may run on this bus (never on one a real drive may be on)."""
    if interface in SIMULATION_INTERFACES:
        return True
    return interface == "socketcan" and channel.startswith(SIMULATION_SOCKETCAN_PREFIX)


class LogFormat(StrEnum):
    """How the daemon writes its log lines: one JSON object per line, or plain text."""

    JSON = "json"
    TEXT = "text"


@dataclass(frozen=True)
class DaemonSettings:
    """``[daemon]``: control socket, where runs are written, log style, idle check period (s),
    and the limits that keep clients from knocking the service over: concurrent connections,
    idle time-out of a connection, replies held for a slow reader.

    Locations are relative to the daemon's working directory.
    """

    socket: Path = field(metadata=setting(doc="control socket of the daemon"))
    output_dir: Path = field(metadata=setting(doc="folder the runs are written to"))
    log_format: LogFormat = field(
        default=LogFormat.JSON, metadata=setting(doc="json (for journald) or text")
    )
    idle_check_s: float = field(
        default=0.1, metadata=setting(unit="s", gt=0.0, doc="period of the idle bus check")
    )
    watchdog_s: float | None = field(
        default=None,
        metadata=setting(unit="s", gt=0.0, doc="systemd watchdog period (default from systemd)"),
    )
    max_clients: int = field(
        default=16,
        metadata=setting(
            ge=1,
            le=1024,
            message="must be 1..1024 connections, got {value}",
            doc="concurrent control connections; more are refused with a one-line JSON error",
        ),
    )
    client_idle_s: float = field(
        default=300.0,
        metadata=setting(
            unit="s", gt=0.0, doc="a connection that sends nothing this long is closed"
        ),
    )
    client_buffer_bytes: int = field(
        default=1 << 20,
        metadata=setting(
            unit="bytes",
            ge=4096,
            le=1 << 30,
            message="must be 4096..1073741824 bytes, got {value}",
            doc="replies held for a client that does not read them; past this it is dropped",
        ),
    )


def _scalar_or_floats(table: Table, key: str) -> float | tuple[float, ...]:
    if isinstance(table.raw(key), list):
        return tuple(float(v) for v in table.get_floats(key))
    return table.get_float(key)


@dataclass(frozen=True)
class SupervisionSettings:
    """The supervision keys of the ``[acquisition]`` table (checked on every cycle)."""

    following_error: float | tuple[float, ...] = field(
        default=0.05,
        metadata=setting(
            unit="rad",
            parse=_scalar_or_floats,
            doc="largest |setpoint - position|, one value or one per joint",
        ),
    )
    position_margin: float = field(
        default=0.02,
        metadata=setting(unit="rad", ge=0.0, doc="how far past its limits a position may be"),
    )
    velocity_margin: float = field(
        default=1.25,
        metadata=setting(
            gt=0.0,
            ge=1.0,
            message="must be >= 1 (a factor of the limit), got {value}",
            doc="a speed above this factor times the velocity limit is a fault",
        ),
    )
    max_overruns: int = field(
        default=3,
        metadata=setting(ge=1, doc="consecutive realtime deadline misses tolerated"),
    )


@dataclass(frozen=True)
class AcquisitionSettings:
    """The ``[acquisition]`` table as written (before the robot and the clock are known), but
    for the keys of :class:`SupervisionSettings`.

    ``queue_s`` is the seconds of cycles the recorder may hold in memory; ``settle_s`` the time
    the final setpoint is held before disabling; ``bus_load_warn`` the bus load fraction above
    which a run is allowed with a warning; ``tpdo_timeout_s`` how long after a SYNC a TPDO
    missing is a fault (TPDOs later than one period but within it are counted as late);
    ``heartbeat_timeout_s`` how long a drive's heartbeat may stay away;
    ``master_node_id`` and ``master_heartbeat_s`` the master's own heartbeat, which every drive
    is told to watch (0x1016, time-out three periods): a drive that misses it stops the robot.
    ``can_trace`` names the raw CAN trace recorded beside every run's log (as written; resolved
    per run by :func:`~drivegain.acquire.cantrace.run_trace_path`).
    """

    robot_path: Path = field(
        metadata=setting(key="robot", path=PathRule.EXISTING, doc="robot TOML, beside this file")
    )
    period_s: float = field(
        default=0.004,
        metadata=setting(
            unit="s",
            gt=0.0,
            ge=1e-4,
            le=0.1,
            message="must be between 0.0001 and 0.1 s, got {value}",
            doc="SYNC period",
        ),
    )
    eds: Path | None = field(
        default=None,
        metadata=setting(path=PathRule.EXISTING, doc="EDS of the drives (default the shipped)"),
    )
    flush_interval_s: float = field(
        default=1.0, metadata=setting(unit="s", gt=0.0, doc="log flushed and fsynced this often")
    )
    queue_s: float = field(
        default=10.0, metadata=setting(unit="s", gt=0.0, doc="cycles the recorder may hold")
    )
    settle_s: float = field(
        default=0.2, metadata=setting(unit="s", ge=0.0, doc="final setpoint held this long")
    )
    bus_load_warn: float = field(
        default=0.7,
        metadata=setting(
            gt=0.0,
            le=1.0,
            message="must be a fraction <= 1, got {value}",
            doc="bus load fraction above which a run is allowed with a warning",
        ),
    )
    rt_priority: int = field(
        default=0,
        metadata=setting(
            ge=0,
            le=99,
            message="SCHED_FIFO priority must be 0..99, got {value}",
            doc="SCHED_FIFO priority of the cycle thread (0: off)",
        ),
    )
    spin_s: float = field(
        default=0.0,
        metadata=setting(
            unit="s",
            ge=0.0,
            le=0.01,
            message="must be between 0 and 0.01 s, got {value}",
            doc="realtime: the last part of each period busy-waited rather than slept (a "
            "SYNC on time whatever the scheduler's wake-up; costs that share of a core and "
            "holds the interpreter meanwhile; 0 = sleep only)",
        ),
    )
    tpdo_timeout_s: float | None = field(
        default=None,
        metadata=setting(
            unit="s",
            gt=0.0,
            doc="SYNC to a missing TPDO that is a fault (default: per clock, see "
            "drivegain.drivers.bus.default_tpdo_timeout)",
        ),
    )
    heartbeat_timeout_s: float = field(
        default=Timeouts.heartbeat_s,
        metadata=setting(
            unit="s",
            gt=Timeouts.heartbeat_producer_s,
            message=f"must exceed the drives' heartbeat period ({Timeouts.heartbeat_producer_s} "
            "s), got {value}",
            doc="a drive whose heartbeat stays away this long is lost (simulated time in lockstep)",
        ),
    )
    master_node_id: int = field(
        default=DEFAULT_MASTER_NODE_ID,
        metadata=setting(
            ge=1,
            le=127,
            message="must be a node id 1..127, got {value}",
            doc="node id of the master's heartbeat (no drive may have it)",
        ),
    )
    master_heartbeat_s: float = field(
        default=DEFAULT_MASTER_HEARTBEAT_S,
        metadata=setting(
            unit="s",
            gt=0.0,
            ge=0.001,
            le=65.535 / CONSUMER_PERIODS,
            message=f"must be 0.001..{65.535 / CONSUMER_PERIODS:.3f} s, got {{value}}",
            doc=f"period of the master's heartbeat; the drives stop after {CONSUMER_PERIODS} "
            "periods without it",
        ),
    )
    can_trace: Path | None = field(
        default=None,
        metadata=setting(
            check=trace_name_problem,
            doc="raw CAN trace of every run (.blf, .asc, .log...), relative to the run's log "
            "folder; {log} is the log's name (--can-trace overrides it)",
        ),
    )


@dataclass(frozen=True, kw_only=True)
class AcquisitionConfig(AcquisitionSettings):
    """A validated acquisition TOML: the ``[acquisition]`` settings and what they lead to.

    ``tpdo_timeout_s`` is resolved (the file's, else the clock's default).
    """

    source: Path = field(metadata=derived(doc="the acquisition TOML"))
    robot: Robot = field(metadata=derived(doc="the robot of robot_path"))
    bus: BusConfig = field(metadata=derived(doc="the [bus] table"))
    simulation: SimConfig | None = field(metadata=derived(doc="the [simulation] table"))
    supervision: Supervision = field(metadata=derived(doc="the supervision settings"))
    daemon: DaemonSettings | None = field(metadata=derived(doc="the [daemon] table"))
    tpdo_timeout_s: float = field(metadata=derived(doc="SYNC to a missing TPDO, s"))

    @property
    def clock(self) -> Clock:
        """Lockstep or realtime: hardware is always realtime."""
        return self.simulation.clock if self.simulation is not None else Clock.REALTIME

    @property
    def queue_capacity(self) -> int:
        """Recorder queue length in records (cycles + events)."""
        return max(64, int(self.queue_s / self.period_s))


def load_acquisition_config(
    path: str | Path, bus_overrides: BusOverrides | None = None
) -> AcquisitionConfig:
    """Load and validate an acquisition TOML.

    Parameters
    ----------
    path
        The TOML. Without a ``[bus]`` table the bus is python-can's own configuration
        (:func:`~drivegain.drivers.bus.bus_config_from_python_can`).
    bus_overrides
        The command line's ``--interface/--channel/--bitrate``, applied over the file's bus.

    Raises
    ------
    ConfigError
        One line naming the file and the key at fault.
    """
    p = Path(path)
    root = read_root(p, {"acquisition", "bus", "simulation", "daemon"})
    a = root.table("acquisition")
    base = p.resolve().parent
    settings = load_table(AcquisitionSettings, a, base_dir=base, also=keys_of(SupervisionSettings))
    limits = load_table(SupervisionSettings, a, also=keys_of(AcquisitionSettings))
    robot = load_robot(settings.robot_path)
    if settings.master_node_id in robot.node_ids:
        raise a.error(
            "master_node_id",
            f"{settings.master_node_id} is the node id of a drive (robot {robot.node_ids})",
        )
    supervision = _supervision(a, limits, robot)
    if root.has("bus"):
        bus = bus_config_from_table(root.table("bus"))
    else:
        bus = bus_config_from_python_can(str(p))
    if bus_overrides is not None:
        bus = with_overrides(bus, **bus_overrides.__dict__, source=str(p))
    sim = sim_config_from_table(root.table("simulation"), base) if root.has("simulation") else None
    if sim is not None:
        check_fault_nodes(sim, robot.node_ids, root.table("simulation"))
    if sim is not None and not simulation_bus_allowed(bus.interface, bus.channel):
        raise root.table("bus").error(
            "interface",
            f"a [simulation] runs on the virtual bus (drives in this process), {IPC_INTERFACE} "
            f"(drives in a child process) or socketcan on a Linux vcan device (drives in a "
            f"child process in realtime, in this one in lockstep), not "
            f"{bus.interface} channel {bus.channel!r}: simulated drives never go on a real bus",
        )
    daemon = load_table(DaemonSettings, root.table("daemon")) if root.has("daemon") else None
    clock = sim.clock if sim is not None else Clock.REALTIME
    period = settings.period_s
    tpdo_timeout = settings.tpdo_timeout_s
    if tpdo_timeout is None:
        tpdo_timeout = default_tpdo_timeout(clock, period)
    elif clock == Clock.REALTIME and tpdo_timeout < period:
        raise a.error(
            "tpdo_timeout_s", f"must be at least one period ({period} s), got {tpdo_timeout}"
        )
    table_values = {f.name: getattr(settings, f.name) for f in fields(AcquisitionSettings)}
    return AcquisitionConfig(
        **{
            **table_values,
            "source": p,
            "robot": robot,
            "bus": bus,
            "simulation": sim,
            "supervision": supervision,
            "daemon": daemon,
            "tpdo_timeout_s": tpdo_timeout,
        }
    )


def _supervision(a: Table, settings: SupervisionSettings, robot: Robot) -> Supervision:
    if isinstance(settings.following_error, tuple):
        if len(settings.following_error) != robot.n:
            raise a.error(
                "following_error",
                f"expected {robot.n} values, got {len(settings.following_error)}",
            )
        fe = np.array(settings.following_error)
    else:
        fe = np.full(robot.n, settings.following_error)
    if np.any(fe <= 0):
        raise a.error("following_error", f"must be > 0 rad, got {fe.tolist()}")
    return Supervision(
        following_error=fe,
        position_margin=settings.position_margin,
        velocity_margin=settings.velocity_margin,
        max_overruns=settings.max_overruns,
    )
