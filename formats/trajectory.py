"""The excitation trajectory file (``TRAJ.json``, contracts §6): the one reader and writer.

Fields beyond the contract's (all optional when reading): ``fourier.harmonics``, ``limits``
(the working limits used, see :meth:`ExcitationLimits.to_dict`), ``start_state`` (q, qd, qdd at
t = 0), ``approach`` / ``retreat`` (the ruckig segments planned from the command's start pose),
``optimisation`` (criterion, payload, seed, budget, starts) and more ``metrics``.

Every stage reads the file through :func:`load_trajectory` (a path) or :func:`parse_trajectory`
(bytes, e.g. the copy attached to a log); planning a motion from it is :mod:`drivegain.excite`'s.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivegain import __version__
from drivegain.config.robot import Robot
from drivegain.errors import ConfigError, DataError, TrajectoryError
from drivegain.fileio import write_atomic
from drivegain.formats.fourier import FourierTrajectory, start_state

FORMAT_VERSION = 1

#: Default margin kept from each position limit, rad (about 5.7°).
POSITION_MARGIN = 0.1
#: Default fraction of the velocity, acceleration and jerk limits the plans may use.
DYNAMIC_FRACTION = 0.95


@dataclass(frozen=True)
class ExcitationLimits:
    """Working limits, joint side, arrays of shape (n,).

    Attributes
    ----------
    lower, upper
        Position range, rad (the robot's range shrunk by ``position_margin``).
    velocity, acceleration, jerk
        Symmetric limits, rad/s, rad/s², rad/s³ (the robot's times ``fraction``).
    position_margin
        The margin kept from each position limit, rad.
    fraction
        The fraction of the robot's velocity, acceleration and jerk limits used.
    """

    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    jerk: np.ndarray
    position_margin: float = POSITION_MARGIN
    fraction: float = DYNAMIC_FRACTION

    @classmethod
    def from_robot(
        cls,
        robot: Robot,
        position_margin: float = POSITION_MARGIN,
        fraction: float = DYNAMIC_FRACTION,
    ) -> ExcitationLimits:
        """Working limits of ``robot``.

        Raises
        ------
        ConfigError
            A joint's position range is not wider than twice the margin (names the robot file
            and the joint), or the margin/fraction are out of range.
        """
        if not (np.isfinite(position_margin) and position_margin >= 0.0):
            raise ConfigError(f"position margin must be >= 0 rad, got {position_margin}")
        if not 0.0 < fraction <= 1.0:
            raise ConfigError(f"limit fraction must be in (0, 1], got {fraction}")
        lower = robot.lower + position_margin
        upper = robot.upper - position_margin
        for i, j in enumerate(robot.joints):
            if not lower[i] < upper[i]:
                raise ConfigError(
                    f"{j.name}: position range {list(j.position_limits)} rad is not wider than "
                    f"twice the margin {position_margin:g} rad kept from each limit",
                    file=robot.source,
                    key=f"joint[{i}].position_limits",
                )
        return cls(
            lower=lower,
            upper=upper,
            velocity=robot.velocity_limits * fraction,
            acceleration=robot.acceleration_limits * fraction,
            jerk=robot.jerk_limits * fraction,
            position_margin=float(position_margin),
            fraction=float(fraction),
        )

    @property
    def n(self) -> int:
        return int(self.lower.shape[0])

    @property
    def middle(self) -> np.ndarray:
        """Middle of each working position range, rad."""
        return 0.5 * (self.lower + self.upper)

    def symmetric(self, order: int) -> np.ndarray:
        """The symmetric limit of derivative ``order`` (1 velocity, 2 acceleration, 3 jerk)."""
        return (self.velocity, self.acceleration, self.jerk)[order - 1]

    def to_dict(self, names: list[str]) -> dict[str, object]:
        """JSON-ready description (stored in the trajectory file)."""
        return {
            "position_margin_rad": self.position_margin,
            "fraction": self.fraction,
            "joints": [
                {
                    "name": name,
                    "position": [float(self.lower[i]), float(self.upper[i])],
                    "velocity": float(self.velocity[i]),
                    "acceleration": float(self.acceleration[i]),
                    "jerk": float(self.jerk[i]),
                }
                for i, name in enumerate(names)
            ],
        }


@dataclass(frozen=True)
class ExcitationFile:
    """A trajectory file's content.

    Attributes
    ----------
    fourier
        The series, with the file's number of periods.
    robot
        Robot name the trajectory was made for.
    joint_names
        Joint names, in order.
    metrics
        ``metrics`` of the file (``cond`` at least).
    limits
        Working limits used to make it, if stored.
    extra
        Every other top-level field, as read.
    path
        Where it was read from.
    """

    fourier: FourierTrajectory
    robot: str
    joint_names: list[str]
    metrics: dict[str, Any]
    limits: ExcitationLimits | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    def check_robot(self, robot: Robot) -> None:
        """Refuse a robot whose joints differ from the file's.

        Raises
        ------
        DataError
            Naming the file and ``joint_names``.
        """
        if list(robot.joint_names) != self.joint_names:
            raise DataError(
                f"made for joints {self.joint_names} of {self.robot!r}, the robot has "
                f"{robot.joint_names}",
                file=self.path,
                key="joint_names",
            )


def trajectory_document(
    fourier: FourierTrajectory,
    robot: Robot,
    metrics: dict[str, Any],
    limits: ExcitationLimits | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The JSON document of a trajectory (contracts §6 plus our extra fields)."""
    q, qd, qdd = start_state(fourier)
    doc: dict[str, Any] = {
        "format_version": FORMAT_VERSION,
        "robot": robot.name,
        "joint_names": list(robot.joint_names),
        "fourier": {
            "base_frequency_hz": float(fourier.base_frequency_hz),
            "harmonics": fourier.harmonics,
            "q0": [float(x) for x in fourier.q0],
            "a": [[float(x) for x in row] for row in fourier.a],
            "b": [[float(x) for x in row] for row in fourier.b],
        },
        "periods": int(fourier.periods),
        "metrics": dict(metrics),
        "start_state": {
            "q": [float(x) for x in q],
            "qd": [float(x) for x in qd],
            "qdd": [float(x) for x in qdd],
        },
    }
    if limits is not None:
        doc["limits"] = limits.to_dict(list(robot.joint_names))
    doc["drivegain_version"] = __version__
    doc.update(extra or {})
    return doc


def save_trajectory(path: str | Path, document: dict[str, Any]) -> Path:
    """Write a trajectory document atomically (temporary file in the same folder, fsync,
    rename), so a reader never sees a half-written file.

    Raises
    ------
    TrajectoryError
        The document holds a non-finite number (JSON has none); nothing is written.
    """
    p = Path(path)
    try:
        text = _dumps(document, 0) + "\n"
    except ValueError as exc:
        raise TrajectoryError(f"{p}: cannot be written: {exc}") from None
    return write_atomic(p, text.encode())


def _dumps(obj: Any, level: int) -> str:
    """JSON with one line per list of numbers (readable, and stable byte for byte)."""
    pad = " " * (level + 1)
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{pad}{json.dumps(str(k))}: {_dumps(v, level + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + " " * level + "}"
    if isinstance(obj, list | tuple) and any(isinstance(v, dict | list | tuple) for v in obj):
        items = [pad + _dumps(v, level + 1) for v in obj]
        return "[\n" + ",\n".join(items) + "\n" + " " * level + "]"
    return json.dumps(obj, allow_nan=False)


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name} (JSON has no NaN or Infinity)")


def _floats(v: Any, key: str, path: Path | None, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise DataError("expected numbers", file=path, key=key) from None
    if a.shape != shape:
        raise DataError(f"expected shape {list(shape)}, got {list(a.shape)}", file=path, key=key)
    if not np.all(np.isfinite(a)):
        raise DataError("holds a non-finite number", file=path, key=key)
    return a


def load_trajectory(path: str | Path) -> ExcitationFile:
    """Read and validate a trajectory file.

    Raises
    ------
    DataError
        One line naming the file and the key at fault (unreadable, not JSON, NaN or Infinity,
        wrong ``format_version``, missing field, wrong shape).
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read: {exc.__class__.__name__}: {exc}", file=p) from None
    return parse_trajectory(data, p)


def _json_object(data: bytes, p: Path | None) -> dict[str, Any]:
    try:
        doc = json.loads(data.decode("utf-8"), parse_constant=_reject_constant)
    except UnicodeDecodeError as exc:
        raise DataError(f"cannot read: {exc.__class__.__name__}: {exc}", file=p) from None
    except (ValueError, RecursionError) as exc:
        raise DataError(f"not a valid trajectory JSON: {exc}", file=p) from None
    if not isinstance(doc, dict):
        raise DataError("expected a JSON object", file=p)
    return doc


def parse_trajectory(data: bytes, path: Path | None = None) -> ExcitationFile:
    """Validate a trajectory document given as bytes (``path`` names it in errors).

    Raises
    ------
    DataError
        As :func:`load_trajectory`.
    """
    p = path
    doc = _json_object(data, p)
    version = doc.get("format_version")
    if version != FORMAT_VERSION:
        raise DataError(
            f"unsupported format_version {version!r} (expected {FORMAT_VERSION})",
            file=p,
            key="format_version",
        )
    for key in ("robot", "joint_names", "fourier", "periods", "metrics"):
        if key not in doc:
            raise DataError("missing", file=p, key=key)
    names = doc["joint_names"]
    if not isinstance(names, list) or not names or not all(isinstance(x, str) for x in names):
        raise DataError("expected a non-empty list of names", file=p, key="joint_names")
    n = len(names)
    periods = doc["periods"]
    if isinstance(periods, bool) or not isinstance(periods, int) or periods < 1:
        raise DataError(f"must be an integer >= 1, got {periods!r}", file=p, key="periods")
    fourier = _fourier(doc["fourier"], n, periods, p)
    metrics = doc["metrics"]
    if not isinstance(metrics, dict):
        raise DataError("expected an object", file=p, key="metrics")
    limits = _limits(doc.get("limits"), n, p) if "limits" in doc else None
    known = {"format_version", "robot", "joint_names", "fourier", "periods", "metrics", "limits"}
    return ExcitationFile(
        fourier=fourier,
        robot=str(doc["robot"]),
        joint_names=list(names),
        metrics=metrics,
        limits=limits,
        extra={k: v for k, v in doc.items() if k not in known},
        path=p,
    )


def _fourier(four: Any, n: int | None, periods: int, p: Path | None) -> FourierTrajectory:
    """The ``fourier`` object of a document (``n`` joints, or as many as ``q0`` has)."""
    if not isinstance(four, dict):
        raise DataError("expected an object", file=p, key="fourier")
    for key in ("base_frequency_hz", "q0", "a", "b"):
        if key not in four:
            raise DataError("missing", file=p, key=f"fourier.{key}")
    f_hz = four["base_frequency_hz"]
    if (
        isinstance(f_hz, bool)
        or not isinstance(f_hz, int | float)
        or not (math.isfinite(f_hz) and f_hz > 0)
    ):
        raise DataError(
            f"must be a finite number > 0, got {f_hz!r}", file=p, key="fourier.base_frequency_hz"
        )
    if n is None:
        n = len(four["q0"]) if isinstance(four["q0"], list) else 0
    a_raw = four["a"]
    h = len(a_raw[0]) if isinstance(a_raw, list) and a_raw and isinstance(a_raw[0], list) else 0
    if h < 1:
        raise DataError("expected one list of harmonics per joint", file=p, key="fourier.a")
    q0 = _floats(four["q0"], "fourier.q0", p, (n,))
    a = _floats(a_raw, "fourier.a", p, (n, h))
    b = _floats(four["b"], "fourier.b", p, (n, h))
    if "harmonics" in four and four["harmonics"] != h:
        raise DataError(f"says {four['harmonics']}, a has {h}", file=p, key="fourier.harmonics")
    return FourierTrajectory(float(f_hz), q0, a, b, periods)


def attached_fourier(attachments: Mapping[str, bytes]) -> FourierTrajectory | None:
    """The series of the first attachment holding a valid ``fourier`` object (contracts §6),
    e.g. the trajectory file attached to a log; ``None`` when there is none."""
    for name, data in attachments.items():
        try:
            doc = _json_object(data, Path(name))
            if "fourier" in doc:
                return _fourier(doc["fourier"], None, 1, Path(name))
        except DataError:
            continue
    return None


def _limits(raw: Any, n: int, path: Path | None) -> ExcitationLimits:
    try:
        joints = raw["joints"]
        if len(joints) != n:
            raise DataError(f"expected {n} joints, got {len(joints)}", file=path, key="limits")
        pos = _floats([j["position"] for j in joints], "limits.joints.position", path, (n, 2))
        vals = {
            k: _floats([j[k] for j in joints], f"limits.joints.{k}", path, (n,))
            for k in ("velocity", "acceleration", "jerk")
        }
        margin = float(raw["position_margin_rad"])
        fraction = float(raw["fraction"])
    except (KeyError, TypeError) as exc:
        raise DataError(
            f"malformed ({exc.__class__.__name__}: {exc})", file=path, key="limits"
        ) from None
    if not (math.isfinite(margin) and math.isfinite(fraction)):
        raise DataError("holds a non-finite number", file=path, key="limits")
    if np.any(pos[:, 0] >= pos[:, 1]) or any(np.any(v <= 0) for v in vals.values()):
        raise DataError("empty position range or non-positive limit", file=path, key="limits")
    return ExcitationLimits(
        lower=pos[:, 0],
        upper=pos[:, 1],
        velocity=vals["velocity"],
        acceleration=vals["acceleration"],
        jerk=vals["jerk"],
        position_margin=margin,
        fraction=fraction,
    )
