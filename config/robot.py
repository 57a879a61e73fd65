"""Robot description (``config/<robot>.toml``, contracts §2): loader and validated record."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from drivegain.config._toml import Table, read_root
from drivegain.config.schema import derived, load_table, setting
from drivegain.errors import ConfigError


class WristFriction(StrEnum):
    """Friction model of a coupled motor (see docs/model.md)."""

    PHYSICAL = "physical"
    PAPER = "paper"


@dataclass(frozen=True)
class MDH:
    """One row of a modified Denavit-Hartenberg table (Khalil): lengths in m, angles in rad."""

    sigma: int = field(
        metadata=setting(
            choices=(0, 1),
            message="must be 0 (revolute) or 1 (prismatic), got {value}",
            doc="0 revolute, 1 prismatic",
        )
    )
    alpha: float = field(metadata=setting(unit="rad", doc="twist about x of the previous frame"))
    d: float = field(metadata=setting(unit="m", doc="distance along x of the previous frame"))
    theta_offset: float = field(metadata=setting(unit="rad", doc="offset of the joint angle"))
    r: float = field(metadata=setting(unit="m", doc="distance along z"))


def _ordered_limits(limits: tuple[float, ...]) -> str | None:
    if limits[0] < limits[1]:
        return None
    return f"lower must be below upper, got {list(limits)}"


@dataclass(frozen=True)
class Joint:
    """One joint and its drive.

    Limits are joint-side: position (rad), velocity (rad/s), acceleration (rad/s²), jerk (rad/s³).
    ``gear_ratio`` is signed (motor angle / joint angle); ``encoder_counts`` per motor revolution;
    ``rated_current`` in A; ``apriori_gain`` in N·m/A at the joint.
    """

    name: str = field(metadata=setting(doc="joint name"))
    mdh: MDH | None = field(metadata=setting(doc="MDH row (required without a URDF)"))
    position_limits: tuple[float, float] = field(
        metadata=setting(
            unit="rad", length=2, magnitude=1e3, check=_ordered_limits, doc="[lower, upper]"
        )
    )
    velocity_limit: float = field(
        metadata=setting(unit="rad/s", gt=0.0, magnitude=1e3, doc="velocity limit")
    )
    acceleration_limit: float = field(
        metadata=setting(unit="rad/s²", gt=0.0, magnitude=1e5, doc="acceleration limit")
    )
    jerk_limit: float = field(
        metadata=setting(unit="rad/s³", gt=0.0, magnitude=1e8, doc="jerk limit")
    )
    gear_ratio: float = field(
        metadata=setting(nonzero=True, magnitude=1e4, doc="motor angle / joint angle, signed")
    )
    encoder_counts: int = field(
        metadata=setting(ge=1, le=2**32, doc="encoder counts per motor turn")
    )
    rated_current: float = field(
        metadata=setting(unit="A", gt=0.0, magnitude=1e4, doc="rated current")
    )
    node_id: int = field(
        metadata=setting(
            ge=1, le=127, message="CANopen node id must be 1..127, got {value}", doc="node id"
        )
    )
    apriori_gain: float = field(
        default=0.0,
        metadata=setting(
            unit="N·m/A",
            magnitude=1e5,
            doc="a priori drive gain, joint side (omitted or 0: the gear ratio)",
        ),
    )


#: Joint keys only acquisition needs (the drives' scaling and addresses, the excitation's
#: limits); identification reads a robot file without them (``load_robot(acquisition=False)``).
ACQUISITION_KEYS = (
    "encoder_counts",
    "rated_current",
    "node_id",
    "acceleration_limit",
    "jerk_limit",
)


def _placeholders(t: Table, index: int) -> dict[str, float | int]:
    """Stand-in values of the acquisition keys a joint table lacks (identification only).

    Never sent to a drive: acquisition loads the robot file with every key required. The
    acceleration limit only scales the random states that find the base parameters.
    """
    velocity = t.get_float("velocity_limit") if t.has("velocity_limit") else 1.0
    acceleration = t.get_float("acceleration_limit") if t.has("acceleration_limit") else None
    acceleration = acceleration if acceleration is not None else 10.0 * abs(velocity)
    values: dict[str, float | int] = {
        "encoder_counts": 1,
        "rated_current": 1.0,
        "node_id": index + 1,
        "acceleration_limit": acceleration,
        "jerk_limit": 10.0 * acceleration,
    }
    return {k: v for k, v in values.items() if not t.has(k)}


@dataclass(frozen=True)
class Coupling:
    """Motor ``motor`` also turns with joint ``joint`` (0-based indices), with the motor's ratio.

    For the TX-40 wrist: motor 6 turns with K6·(q5 + q6), i.e. ``Coupling(motor=5, joint=4)``.
    """

    motor: int
    joint: int


def _urdf(table: Table, key: str) -> Path:
    urdf = (Path(table.file).parent / table.get_str(key)).resolve()
    if not urdf.is_file():
        raise table.error(key, f"file not found: {urdf}")
    return urdf


@dataclass(frozen=True)
class Robot:
    """A validated robot description. Arrays are indexed by joint (0-based)."""

    name: str = field(metadata=setting(doc="robot name"))
    joints: tuple[Joint, ...] = field(metadata=derived(doc="the [[joint]] tables"))
    couplings: tuple[Coupling, ...] = field(default=(), metadata=derived(doc="[[coupling]]"))
    gravity: np.ndarray = field(
        default_factory=lambda: np.array([0.0, 0.0, -9.81]),
        metadata=setting(unit="m/s²", length=3, magnitude=100.0, doc="gravity in the base frame"),
    )
    wrist_friction: WristFriction = field(
        default=WristFriction.PHYSICAL, metadata=setting(doc="friction form of a coupled motor")
    )
    urdf: Path | None = field(
        default=None, metadata=setting(parse=_urdf, doc="URDF file instead of the MDH rows")
    )
    source: Path | None = field(default=None, metadata=derived(doc="the robot TOML"))
    missing: tuple[str, ...] = field(
        default=(),
        metadata=derived(doc="acquisition keys absent from the file (identification only)"),
    )
    apriori_from_gear_ratio: tuple[str, ...] = field(
        default=(), metadata=derived(doc="joints whose a priori gain is their gear ratio")
    )

    @property
    def n(self) -> int:
        """Number of joints."""
        return len(self.joints)

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def gear_ratios(self) -> np.ndarray:
        return np.array([j.gear_ratio for j in self.joints])

    @property
    def apriori_gains(self) -> np.ndarray:
        return np.array([j.apriori_gain for j in self.joints])

    @property
    def lower(self) -> np.ndarray:
        """Lower position limits, rad."""
        return np.array([j.position_limits[0] for j in self.joints])

    @property
    def upper(self) -> np.ndarray:
        """Upper position limits, rad."""
        return np.array([j.position_limits[1] for j in self.joints])

    @property
    def velocity_limits(self) -> np.ndarray:
        return np.array([j.velocity_limit for j in self.joints])

    @property
    def acceleration_limits(self) -> np.ndarray:
        return np.array([j.acceleration_limit for j in self.joints])

    @property
    def jerk_limits(self) -> np.ndarray:
        return np.array([j.jerk_limit for j in self.joints])

    @property
    def node_ids(self) -> list[int]:
        return [j.node_id for j in self.joints]

    def transmission(self) -> np.ndarray:
        """The matrix K with motor angles q_m = K·q (rad): diag(gear ratios) plus the couplings."""
        k = np.diag(self.gear_ratios)
        for c in self.couplings:
            k[c.motor, c.joint] = self.joints[c.motor].gear_ratio
        return k


def load_robot(path: str | Path, *, acquisition: bool = True) -> Robot:
    """Load and validate a robot description.

    Parameters
    ----------
    path
        The robot TOML.
    acquisition
        Require the keys only acquisition needs (:data:`ACQUISITION_KEYS`: encoder counts,
        rated currents, node ids, acceleration and jerk limits). Identification passes False:
        absent ones get stand-in values never sent to a drive, listed in ``Robot.missing``.

    A joint's a priori gain omitted or 0 is its gear ratio (listed in
    ``Robot.apriori_from_gear_ratio``).

    Raises
    ------
    ConfigError
        One line naming the file and the key at fault.
    """
    p = Path(path)
    root = read_root(p, {"robot", "coupling", "joint"})
    r = root.table("robot")
    joint_tables = root.tables("joint")
    missing: list[str] = []
    loaded = []
    for i, t in enumerate(joint_tables):
        # "mdh" may be absent: checked below, once [robot] says whether a URDF replaces it
        given: dict[str, Any] = {} if t.has("mdh") else {"mdh": None}
        if not acquisition:
            stand_in = _placeholders(t, i)
            missing += [f"joint[{i}].{k}" for k in stand_in]
            given.update(stand_in)
        loaded.append(load_table(Joint, t, **given))
    from_ratio = tuple(j.name for j in loaded if j.apriori_gain == 0.0)
    joints = tuple(
        replace(j, apriori_gain=j.gear_ratio) if j.apriori_gain == 0.0 else j for j in loaded
    )
    if not joints:
        raise root.error("joint", "at least one [[joint]] is required")
    _unique(root, "joint", [j.name for j in joints], "name")
    if acquisition or not any(k.endswith(".node_id") for k in missing):
        _unique(root, "joint", [j.node_id for j in joints], "node_id")
    couplings = []
    for t in root.tables("coupling", required=False):
        t.reject_unknown({"motor", "joint"})
        motor, joint = t.get_int("motor"), t.get_int("joint")
        for key, v in (("motor", motor), ("joint", joint)):
            if not 1 <= v <= len(joints):
                raise t.error(key, f"must be a joint number 1..{len(joints)}, got {v}")
        if motor == joint:
            raise t.error("joint", "a motor cannot be coupled to its own joint")
        couplings.append(Coupling(motor=motor - 1, joint=joint - 1))
    if len({c.motor for c in couplings}) != len(couplings):
        raise root.error("coupling", "at most one coupling per motor")
    robot = load_table(
        Robot,
        r,
        joints=joints,
        couplings=tuple(couplings),
        source=p,
        missing=tuple(missing),
        apriori_from_gear_ratio=from_ratio,
    )
    if robot.urdf is None:
        for t, j in zip(joint_tables, joints, strict=True):
            if j.mdh is None:
                t.raw("mdh")  # raises "missing": without a URDF every joint needs its MDH row
    return robot


def _unique(t: Table, name: str, values: list[object], what: str) -> None:
    seen: set[object] = set()
    for i, v in enumerate(values):
        if v in seen:
            raise ConfigError(f"duplicate {what} {v!r}", file=t.file, key=f"{name}[{i}].{what}")
        seen.add(v)
