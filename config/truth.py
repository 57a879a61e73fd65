"""The simulated robot's true parameters (``config/sim/<robot>-truth.toml``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drivegain.config._toml import read_root
from drivegain.config.inertia import physical_violation
from drivegain.config.schema import SettingError, derived, load_table, setting


@dataclass(frozen=True)
class LinkTruth:
    """True parameters of one link and its drive chain (a ``[[link]]`` table).

    Raises
    ------
    SettingError
        The inertial parameters are not those of a real body (names ``inertia``).
    """

    mass: float = field(metadata=setting(unit="kg", gt=0.0, magnitude=1e4, doc="mass"))
    first_moment: np.ndarray = field(
        metadata=setting(unit="kg·m", length=3, magnitude=1e4, doc="MX MY MZ in the link frame")
    )
    inertia: np.ndarray = field(
        metadata=setting(
            unit="kg·m²", length=6, magnitude=1e5, doc="XX XY XZ YY YZ ZZ at the frame origin"
        )
    )
    Ia: float = field(
        metadata=setting(unit="kg·m²", magnitude=1e5, doc="rotor inertia, joint side")
    )
    Fv: float = field(metadata=setting(unit="N·m·s/rad", magnitude=1e5, doc="viscous friction"))
    Fc: float = field(metadata=setting(unit="N·m", magnitude=1e5, doc="Coulomb friction"))
    offset: float = field(default=0.0, metadata=setting(unit="N·m", doc="torque offset"))

    def __post_init__(self) -> None:
        why = physical_violation(self.mass, self.first_moment, self.inertia)
        if why is not None:
            raise SettingError("inertia", why)


@dataclass(frozen=True)
class Truth:
    """The simulator's truth (the ``[truth]`` table and the links): links, coupled-motor
    friction and true drive gains."""

    robot: str = field(metadata=setting(doc="robot name"))
    links: tuple[LinkTruth, ...] = field(metadata=derived(doc="the [[link]] tables"))
    gains: np.ndarray = field(
        metadata=setting(
            unit="N·m/A", magnitude=1e5, doc="true drive gains, one per link, non-zero"
        )
    )
    fvm: float = field(
        default=0.0, metadata=setting(key="fvm6", unit="N·m·s/rad", doc="coupled motor viscous")
    )
    fcm: float = field(
        default=0.0, metadata=setting(key="fcm6", unit="N·m", doc="coupled motor Coulomb")
    )
    source: Path | None = field(default=None, metadata=derived(doc="the truth TOML"))


def load_truth(path: str | Path, n_links: int | None = None) -> Truth:
    """Load and validate a simulation truth file.

    Raises
    ------
    ConfigError
        One line naming the file and the key at fault.
    """
    p = Path(path)
    root = read_root(p, {"truth", "link"})
    t = root.table("truth")
    links = tuple(load_table(LinkTruth, lt) for lt in root.tables("link"))
    n = len(links)
    if n_links is not None and n != n_links:
        raise root.error("link", f"expected {n_links} [[link]] tables, got {n}")
    truth = load_table(Truth, t, links=links, source=p)
    if len(truth.gains) != n:
        raise t.error("gains", f"expected {n} values, got {len(truth.gains)}")
    if np.any(truth.gains == 0.0):
        raise t.error("gains", "gains must be non-zero")
    return truth
