"""The excitation trajectory file (``TRAJ.json``, contracts §6) and the motion API.

Fields beyond the contract's (all optional when reading): ``fourier.harmonics``, ``limits``
(the working limits used, see :meth:`ExcitationLimits.to_dict`), ``start_state`` (q, qd, qdd at
t = 0), ``approach`` / ``retreat`` (the ruckig segments planned from the command's start pose),
``optimisation`` (criterion, payload, seed, budget, starts) and more ``metrics``.

The motion API (:class:`Motion`, :func:`plan_motion`, :func:`plan_stop`, :func:`check_limits`)
lives in :mod:`.motion` and :mod:`.limits` and is re-exported here.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivegain import __version__
from drivegain.config.robot import Robot
from drivegain.errors import DataError
from drivegain.excite.fourier import FourierTrajectory, start_state
from drivegain.excite.limits import ExcitationLimits, check_limits
from drivegain.excite.motion import Motion, Phase, check_motion, plan_motion, plan_stop

__all__ = [
    "FORMAT_VERSION",
    "ExcitationFile",
    "Motion",
    "Phase",
    "check_limits",
    "check_motion",
    "load_trajectory",
    "plan_motion",
    "plan_stop",
    "save_trajectory",
    "trajectory_document",
]

FORMAT_VERSION = 1


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

    def plan(self, robot: Robot, q_start: np.ndarray, periods: int | None = None) -> Motion:
        """:func:`plan_motion` with the working limits stored in the file (if any)."""
        self.check_robot(robot)
        return plan_motion(robot, self.fourier, q_start, periods, limits=self.limits)


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
    ValueError
        The document holds a non-finite number (JSON has none).
    """
    p = Path(path)
    text = _dumps(document, 0) + "\n"
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


def write_atomic(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file and a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        # mkstemp creates 0600; give the file the usual permissions (umask applied).
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name} (JSON has no NaN or Infinity)")


def _floats(v: Any, key: str, path: Path, shape: tuple[int, ...]) -> np.ndarray:
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
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot read: {exc.__class__.__name__}: {exc}", file=p) from None
    try:
        doc = json.loads(text, parse_constant=_reject_constant)
    except ValueError as exc:
        raise DataError(f"not a valid trajectory JSON: {exc}", file=p) from None
    if not isinstance(doc, dict):
        raise DataError("expected a JSON object", file=p)
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
    four = doc["fourier"]
    if not isinstance(four, dict):
        raise DataError("expected an object", file=p, key="fourier")
    for key in ("base_frequency_hz", "q0", "a", "b"):
        if key not in four:
            raise DataError("missing", file=p, key=f"fourier.{key}")
    f_hz = four["base_frequency_hz"]
    if isinstance(f_hz, bool) or not isinstance(f_hz, int | float) or not f_hz > 0:
        raise DataError(
            f"must be a number > 0, got {f_hz!r}", file=p, key="fourier.base_frequency_hz"
        )
    a_raw = four["a"]
    h = len(a_raw[0]) if isinstance(a_raw, list) and a_raw and isinstance(a_raw[0], list) else 0
    if h < 1:
        raise DataError("expected one list of harmonics per joint", file=p, key="fourier.a")
    q0 = _floats(four["q0"], "fourier.q0", p, (n,))
    a = _floats(a_raw, "fourier.a", p, (n, h))
    b = _floats(four["b"], "fourier.b", p, (n, h))
    if "harmonics" in four and four["harmonics"] != h:
        raise DataError(f"says {four['harmonics']}, a has {h}", file=p, key="fourier.harmonics")
    periods = doc["periods"]
    if isinstance(periods, bool) or not isinstance(periods, int) or periods < 1:
        raise DataError(f"must be an integer >= 1, got {periods!r}", file=p, key="periods")
    metrics = doc["metrics"]
    if not isinstance(metrics, dict):
        raise DataError("expected an object", file=p, key="metrics")
    limits = _limits(doc.get("limits"), n, p) if "limits" in doc else None
    known = {"format_version", "robot", "joint_names", "fourier", "periods", "metrics", "limits"}
    return ExcitationFile(
        fourier=FourierTrajectory(float(f_hz), q0, a, b, periods),
        robot=str(doc["robot"]),
        joint_names=list(names),
        metrics=metrics,
        limits=limits,
        extra={k: v for k, v in doc.items() if k not in known},
        path=p,
    )


def _limits(raw: Any, n: int, path: Path) -> ExcitationLimits:
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
