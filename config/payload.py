"""Payload description (``config/payloads/<name>.toml``, contracts §3)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drivegain.config._toml import read_root
from drivegain.config.inertia import physical_violation
from drivegain.config.schema import load_table, setting

#: Payload parameter names in the order of the regressor's inertial columns of one link.
PAYLOAD_PARAMS = ("XX", "XY", "XZ", "YY", "YZ", "ZZ", "MX", "MY", "MZ", "M")
_KNOWN_ALIASES = {
    "mass": "M",
    "m": "M",
    "mx": "MX",
    "my": "MY",
    "mz": "MZ",
    "xx": "XX",
    "xy": "XY",
    "xz": "XZ",
    "yy": "YY",
    "yz": "YZ",
    "zz": "ZZ",
}


@dataclass(frozen=True)
class Payload:
    """A payload fixed to a link (frame of the payload = frame of that link).

    ``values`` holds the 10 inertial parameters in :data:`PAYLOAD_PARAMS` order (kg·m², kg·m,
    kg); entries not given in the file are NaN. ``known`` lists the names treated as known.
    ``link`` is 1-based as in the file.
    """

    name: str
    link: int
    values: np.ndarray
    known: tuple[str, ...]
    source: Path | None = None

    @property
    def mass(self) -> float:
        return float(self.values[9])

    def known_mask(self) -> np.ndarray:
        """Boolean mask over :data:`PAYLOAD_PARAMS` of the known parameters."""
        return np.array([p in self.known for p in PAYLOAD_PARAMS])


@dataclass(frozen=True)
class PayloadTable:
    """The ``[payload]`` table as written (contracts §3); :class:`Payload` is what it describes."""

    name: str = field(metadata=setting(doc="payload name"))
    link: int = field(metadata=setting(ge=1, doc="link it is fixed to, 1-based"))
    mass: float | None = field(
        default=None, metadata=setting(unit="kg", gt=0.0, magnitude=1e4, doc="mass")
    )
    first_moment: np.ndarray | None = field(
        default=None,
        metadata=setting(unit="kg·m", length=3, magnitude=1e4, doc="MX MY MZ in the link frame"),
    )
    inertia: np.ndarray | None = field(
        default=None,
        metadata=setting(
            unit="kg·m²", length=6, magnitude=1e5, doc="XX XY XZ YY YZ ZZ at the frame origin"
        ),
    )
    known: tuple[str, ...] = field(
        default=("mass",), metadata=setting(doc="parameters known to IDIM-WTLS (others identified)")
    )


def load_payload(path: str | Path, n_links: int | None = None) -> Payload:
    """Load and validate a payload file.

    Parameters
    ----------
    path
        The TOML file.
    n_links
        Number of links of the robot, to check ``link`` against (optional).

    Raises
    ------
    ConfigError
        One line naming the file and the key at fault.
    """
    p = Path(path)
    root = read_root(p, {"payload"})
    t = root.table("payload")
    table = load_table(PayloadTable, t)
    if n_links is not None and table.link > n_links:
        raise t.error("link", f"the robot has {n_links} links, got {table.link}")
    values = np.full(10, np.nan)
    if table.mass is not None:
        values[9] = table.mass
    if table.first_moment is not None:
        values[6:9] = table.first_moment
    if table.inertia is not None:
        values[0:6] = table.inertia
    known = []
    for name in table.known:
        canon = _KNOWN_ALIASES.get(name.lower())
        if canon is None:
            raise t.error("known", f"unknown parameter {name!r} (use mass, MX.., XX..)")
        if np.isnan(values[PAYLOAD_PARAMS.index(canon)]):
            raise t.error("known", f"{name!r} is listed as known but has no value")
        known.append(canon)
    if not known:
        raise t.error("known", "at least one parameter (normally the mass) must be known")
    if not np.any(np.isnan(values)):
        why = physical_violation(values[9], values[6:9], values[0:6])
        if why is not None:
            raise t.error("inertia", why)
    elif np.isnan(values[9]):
        raise t.error("mass", "missing")
    return Payload(name=table.name, link=table.link, values=values, known=tuple(known), source=p)
