"""The ``[simulation]`` table of an acquisition TOML: how the simulated cell behaves."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from drivegain.config import resource_path
from drivegain.config._toml import Table
from drivegain.config.robot import WristFriction
from drivegain.config.schema import PathRule, load_table, setting
from drivegain.drivers.clock import Clock
from drivegain.drivers.faults import FaultSpec
from drivegain.errors import ConfigError

#: The simulation truth used when ``truth`` is not set (file shipped with drivegain).
DEFAULT_TRUTH = "sim/tx40-truth.toml"


def _default_truth() -> Path:
    return resource_path(DEFAULT_TRUTH)


@dataclass(frozen=True)
class SimConfig:
    """The ``[simulation]`` table.

    Attributes
    ----------
    clock
        :class:`~drivegain.drivers.clock.Clock` (a string ``lockstep`` / ``realtime`` is
        converted).
    truth
        Simulation truth file (true parameters and gains).
    payload
        Payload mounted on the simulated robot, if any.
    seed
        Seed of the current noise.
    current_noise_nm
        Standard deviation of each drive's current-loop error, as joint torque of that drive
        (N·m); the simulated torque is ``V(i_ref + noise) g``.
    faults
        Injected faults (``[[simulation.fault]]`` tables).
    friction
        Friction form of the coupled wrist; ``None``: the robot's.
    initial_position
        Joint positions at power-on (rad); ``None``: all zero.
    max_step_s
        Largest internal integration step (s); the step is the period divided by an integer >= 2.
    bandwidth_hz
        Velocity-loop bandwidth of the simulated drives (Hz).
    history_s
        Simulated seconds of truth kept for :meth:`SimulatedCell.joint_torque_history`.
    """

    clock: Clock = field(
        default=Clock.LOCKSTEP, metadata=setting(doc="lockstep (simulated time) or realtime")
    )
    truth: Path = field(
        default_factory=_default_truth,
        metadata=setting(
            path=PathRule.EXISTING_OR_SHIPPED,
            doc=f"simulation truth file (default the shipped {DEFAULT_TRUTH})",
        ),
    )
    payload: Path | None = field(
        default=None,
        metadata=setting(
            path=PathRule.EXISTING_OR_SHIPPED, doc="payload mounted on the simulated robot"
        ),
    )
    seed: int = field(default=0, metadata=setting(ge=0, doc="seed of the current noise"))
    current_noise_nm: float = field(
        default=0.5,
        metadata=setting(
            unit="N·m", ge=0.0, doc="current-loop error of each drive as joint torque, 1 sigma"
        ),
    )
    faults: tuple[FaultSpec, ...] = field(
        default=(), metadata=setting(key="fault", doc="injected faults ([[simulation.fault]])")
    )
    friction: WristFriction | None = field(
        default=None,
        metadata=setting(doc="friction form of the coupled wrist (default the robot's)"),
    )
    initial_position: tuple[float, ...] | None = field(
        default=None,
        metadata=setting(unit="rad", doc="joint positions at power-on (default all zero)"),
    )
    max_step_s: float = field(
        default=0.0005, metadata=setting(unit="s", gt=0.0, doc="largest internal step")
    )
    bandwidth_hz: float = field(
        default=60.0, metadata=setting(unit="Hz", gt=0.0, doc="velocity-loop bandwidth")
    )
    history_s: float = field(
        default=120.0, metadata=setting(unit="s", gt=0.0, doc="simulated truth kept for tests")
    )

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "clock", Clock(self.clock))
        except ValueError:
            clocks = tuple(c.value for c in Clock)
            raise ConfigError(
                f"simulation clock must be one of {clocks}, got {self.clock!r}"
            ) from None
        if self.friction is not None:
            try:
                object.__setattr__(self, "friction", WristFriction(self.friction))
            except ValueError:
                raise ConfigError(
                    f"friction must be physical or paper, got {self.friction!r}"
                ) from None


def sim_config_from_table(table: Table, base_dir: Path) -> SimConfig:
    """Read the ``[simulation]`` table of an acquisition TOML (keys: see :class:`SimConfig`).

    Relative paths are relative to ``base_dir``, then to the files shipped with drivegain.
    ``[[simulation.fault]]`` tables: see :func:`drivegain.drivers.faults.fault_from_table`.

    Raises
    ------
    ConfigError
        One line naming the file and key at fault.
    """
    return load_table(SimConfig, table, base_dir=base_dir)


def check_fault_nodes(sim: SimConfig, node_ids: Sequence[int], table: Table) -> None:
    """Refuse a ``[[simulation.fault]]`` whose node is not a drive of the robot.

    Checked when the acquisition TOML is loaded (the robot's node ids are known then), so the
    error names the file and the key, e.g. ``simulation.fault[0].node``, before anything runs.

    Parameters
    ----------
    sim
        The ``[simulation]`` table as read.
    node_ids
        CANopen node ids of the robot's drives.
    table
        The ``[simulation]`` table itself (file and key path of the message).

    Raises
    ------
    ConfigError
        Naming the file, ``simulation.fault[i].node`` and the node ids there are.
    """
    known = sorted(set(node_ids))
    for i, spec in enumerate(sim.faults):
        if spec.node is not None and spec.node not in known:
            raise ConfigError(
                f"{spec.kind}: no drive has node id {spec.node} "
                f"(the robot's drives are {', '.join(str(n) for n in known)})",
                file=table.file,
                key=f"{table.key or 'simulation'}.fault[{i}].node",
            )
