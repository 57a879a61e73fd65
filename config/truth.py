"""The simulated robot's true parameters (``config/sim/<robot>-truth.toml``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivegain.config._toml import Table, read_toml
from drivegain.config.inertia import physical_violation


@dataclass(frozen=True)
class LinkTruth:
    """True parameters of one link and its drive chain (kg, kg·m, kg·m², N·m·s/rad, N·m)."""

    mass: float
    first_moment: np.ndarray
    inertia: np.ndarray
    Ia: float
    Fv: float
    Fc: float
    offset: float


@dataclass(frozen=True)
class Truth:
    """The simulator's truth: links, coupled-motor friction and true drive gains (N·m/A)."""

    robot: str
    links: tuple[LinkTruth, ...]
    gains: np.ndarray
    fvm: float
    fcm: float
    source: Path | None = None


def load_truth(path: str | Path, n_links: int | None = None) -> Truth:
    """Load and validate a simulation truth file."""
    p = Path(path)
    root = Table(read_toml(p), p)
    root.reject_unknown({"truth", "link"})
    t = root.table("truth")
    t.reject_unknown({"robot", "gains", "fvm6", "fcm6"})
    links = []
    for lt in root.tables("link"):
        lt.reject_unknown({"mass", "first_moment", "inertia", "Ia", "Fv", "Fc", "offset"})
        mass = lt.get_float("mass", positive=True)
        ms = lt.get_floats("first_moment", length=3)
        inertia = lt.get_floats("inertia", length=6)
        why = physical_violation(mass, ms, inertia)
        if why is not None:
            raise lt.error("inertia", why)
        links.append(
            LinkTruth(
                mass=mass,
                first_moment=ms,
                inertia=inertia,
                Ia=lt.get_float("Ia"),
                Fv=lt.get_float("Fv"),
                Fc=lt.get_float("Fc"),
                offset=lt.get_float("offset", default=0.0),
            )
        )
    n = len(links)
    if n_links is not None and n != n_links:
        raise root.error("link", f"expected {n_links} [[link]] tables, got {n}")
    gains = t.get_floats("gains", length=n)
    if np.any(gains == 0.0):
        raise t.error("gains", "gains must be non-zero")
    return Truth(
        robot=t.get_str("robot"),
        links=tuple(links),
        gains=gains,
        fvm=t.get_float("fvm6", default=0.0),
        fcm=t.get_float("fcm6", default=0.0),
        source=p,
    )
