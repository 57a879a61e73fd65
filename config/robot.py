"""Robot description (``config/<robot>.toml``, contracts §2): loader and validated record."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np

from drivegain.config._toml import Table, read_toml
from drivegain.errors import ConfigError


class WristFriction(StrEnum):
    """Friction model of a coupled motor (see docs/model.md)."""

    PHYSICAL = "physical"
    PAPER = "paper"


@dataclass(frozen=True)
class MDH:
    """One row of a modified Denavit-Hartenberg table (Khalil): lengths in m, angles in rad."""

    sigma: int
    alpha: float
    d: float
    theta_offset: float
    r: float


@dataclass(frozen=True)
class Joint:
    """One joint and its drive.

    Limits are joint-side: position (rad), velocity (rad/s), acceleration (rad/s²), jerk (rad/s³).
    ``gear_ratio`` is signed (motor angle / joint angle); ``encoder_counts`` per motor revolution;
    ``rated_current`` in A; ``apriori_gain`` in N·m/A at the joint.
    """

    name: str
    mdh: MDH | None
    position_limits: tuple[float, float]
    velocity_limit: float
    acceleration_limit: float
    jerk_limit: float
    gear_ratio: float
    encoder_counts: int
    rated_current: float
    node_id: int
    apriori_gain: float


@dataclass(frozen=True)
class Coupling:
    """Motor ``motor`` also turns with joint ``joint`` (0-based indices), with the motor's ratio.

    For the TX-40 wrist: motor 6 turns with K6·(q5 + q6), i.e. ``Coupling(motor=5, joint=4)``.
    """

    motor: int
    joint: int


@dataclass(frozen=True)
class Robot:
    """A validated robot description. Arrays are indexed by joint (0-based)."""

    name: str
    joints: tuple[Joint, ...]
    couplings: tuple[Coupling, ...] = ()
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    wrist_friction: WristFriction = WristFriction.PHYSICAL
    urdf: Path | None = None
    source: Path | None = None

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


_JOINT_KEYS = {
    "name",
    "mdh",
    "position_limits",
    "velocity_limit",
    "acceleration_limit",
    "jerk_limit",
    "gear_ratio",
    "encoder_counts",
    "rated_current",
    "node_id",
    "apriori_gain",
}


def _load_joint(t: Table, need_mdh: bool) -> Joint:
    t.reject_unknown(_JOINT_KEYS)
    mdh = None
    if need_mdh or t.has("mdh"):
        m = t.table("mdh")
        m.reject_unknown({"sigma", "alpha", "d", "theta_offset", "r"})
        sigma = m.get_int("sigma")
        if sigma not in (0, 1):
            raise m.error("sigma", f"must be 0 (revolute) or 1 (prismatic), got {sigma}")
        mdh = MDH(
            sigma=sigma,
            alpha=m.get_float("alpha"),
            d=m.get_float("d"),
            theta_offset=m.get_float("theta_offset"),
            r=m.get_float("r"),
        )
    lim = t.get_floats("position_limits", length=2)
    if not lim[0] < lim[1]:
        raise t.error("position_limits", f"lower must be below upper, got {lim.tolist()}")
    return Joint(
        name=t.get_str("name"),
        mdh=mdh,
        position_limits=(float(lim[0]), float(lim[1])),
        velocity_limit=t.get_float("velocity_limit", positive=True),
        acceleration_limit=t.get_float("acceleration_limit", positive=True),
        jerk_limit=t.get_float("jerk_limit", positive=True),
        gear_ratio=t.get_float("gear_ratio", nonzero=True),
        encoder_counts=t.get_int("encoder_counts", minimum=1),
        rated_current=t.get_float("rated_current", positive=True),
        node_id=_node_id(t),
        apriori_gain=t.get_float("apriori_gain", nonzero=True),
    )


def _node_id(t: Table) -> int:
    nid = t.get_int("node_id")
    if not 1 <= nid <= 127:
        raise t.error("node_id", f"CANopen node id must be 1..127, got {nid}")
    return nid


def load_robot(path: str | Path) -> Robot:
    """Load and validate a robot description.

    Raises
    ------
    ConfigError
        One line naming the file and the key at fault.
    """
    p = Path(path)
    root = Table(read_toml(p), p)
    root.reject_unknown({"robot", "coupling", "joint"})
    r = root.table("robot")
    r.reject_unknown({"name", "gravity", "wrist_friction", "urdf"})
    urdf = None
    if r.has("urdf"):
        urdf = (p.parent / r.get_str("urdf")).resolve()
        if not urdf.is_file():
            raise r.error("urdf", f"file not found: {urdf}")
    joints = tuple(_load_joint(t, need_mdh=urdf is None) for t in root.tables("joint"))
    if not joints:
        raise root.error("joint", "at least one [[joint]] is required")
    _unique(root, "joint", [j.name for j in joints], "name")
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
    gravity = r.get_floats("gravity", length=3) if r.has("gravity") else np.array([0, 0, -9.81])
    return Robot(
        name=r.get_str("name"),
        joints=joints,
        couplings=tuple(couplings),
        gravity=gravity,
        wrist_friction=WristFriction(
            r.get_str("wrist_friction", default="physical", choices=("physical", "paper"))
        ),
        urdf=urdf,
        source=p,
    )


def _unique(t: Table, name: str, values: list[object], what: str) -> None:
    seen: set[object] = set()
    for i, v in enumerate(values):
        if v in seen:
            raise ConfigError(f"duplicate {what} {v!r}", file=t.file, key=f"{name}[{i}].{what}")
        seen.add(v)
