"""The runs of an identification: reading the logs, their roles, their payload, given gains.

Each log's ``drivegain.run`` metadata says what it is (``run``: ``unloaded``/``loaded``,
``payload``: a name or ``none``): :func:`check_roles` refuses a loaded run given as the
unloaded one (or the reverse: every gain would come out with the wrong sign) and the same run
given twice (the solution is then not unique). Without ``--payload``,
:func:`attached_payload` takes the payload TOML attached to the loaded log.
"""

from __future__ import annotations

import hashlib
import json
import math
import tempfile
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drivegain.config._toml import Table, read_toml
from drivegain.config.payload import Payload, load_payload
from drivegain.config.robot import Robot
from drivegain.errors import ConfigError, DataError, InputError
from drivegain.formats.log import METADATA_NAME
from drivegain.formats.logreader import RunLog, read_run
from drivegain.identify.procedure import GivenGains
from drivegain.identify.timebase import TimeBase, uniform_samples

GAINS_KEYWORDS = ("apriori", "gear-ratios")
#: ``--current``: which current of the log is the torque's image.
CURRENT_CHANNELS = ("reference", "measured")


def load_gains(spec: str, robot: Robot) -> GivenGains:
    """Gains given with ``--gains``.

    Raises
    ------
    InputError
        Unknown keyword, unreadable file, wrong count, zero or non-finite values.
    """
    if spec == "apriori":
        return GivenGains(robot.apriori_gains, None, "apriori")
    if spec == "gear-ratios":
        return GivenGains(robot.gear_ratios, None, "gear ratios")
    path = Path(spec)
    if not path.exists():
        raise InputError(
            f"expected {' or '.join(GAINS_KEYWORDS)}, a TOML file or a report.json; "
            f"no such file {spec!r}",
            key="--gains",
        )
    if path.suffix.lower() == ".json":
        values, std = _gains_from_report(path, robot.n)
    else:
        t = Table(read_toml(path), path)
        t.reject_unknown({"values", "std"})
        values = t.get_floats("values", length=robot.n)
        std = t.get_floats("std", length=robot.n) if t.has("std") else None
        if np.any(values == 0.0):
            raise t.error("values", "gains must be non-zero")
        if std is not None and np.any(std < 0.0):
            raise t.error("std", "standard deviations must be >= 0")
    return GivenGains(values, std, str(path))


def _gains_from_report(path: Path, n: int) -> tuple[np.ndarray, np.ndarray | None]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise DataError(f"not a readable JSON report ({exc})", file=path) from None
    gains = doc.get("gains") if isinstance(doc, dict) else None
    if not isinstance(gains, list) or len(gains) != n:
        count = len(gains) if isinstance(gains, list) else 0
        raise DataError(f"expected {n} gains, found {count}", file=path, key="gains")
    values, stds = [], []
    for i, g in enumerate(gains):
        v = g.get("value") if isinstance(g, dict) else None
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v == 0:
            raise DataError(f"not a non-zero number: {v!r}", file=path, key=f"gains[{i}].value")
        values.append(float(v))
        s = g.get("std")
        stds.append(float(s) if isinstance(s, int | float) and not isinstance(s, bool) else None)
    std = None if any(s is None for s in stds) else np.array(stds, dtype=float)
    return np.array(values), std


# --------------------------------------------------------------------------------------------
# Metadata: roles and payload


@dataclass(frozen=True)
class RunHeader:
    """A log's metadata and attachments, read without its messages."""

    path: Path
    meta: dict[str, str]
    attachments: dict[str, bytes]

    @property
    def kind(self) -> str | None:
        """``unloaded`` or ``loaded`` as the metadata says (``run``, else ``payload``)."""
        run = self.meta.get("run", "")
        if run in ("unloaded", "loaded"):
            return run
        payload = self.meta.get("payload")
        if payload is None or payload == "":
            return None
        return "unloaded" if payload == "none" else "loaded"

    def describe(self) -> str:
        """``run 'loaded', payload 'x'`` for messages."""
        return f"run {self.meta.get('run', '?')!r}, payload {self.meta.get('payload', '?')!r}"


def read_header(path: Path) -> RunHeader:
    """Metadata and attachments of a log; from its summary when it has one (fast), else by
    reading the whole log (a ``.part`` file).

    Raises
    ------
    DataError
        The log cannot be read (see :func:`~drivegain.formats.logreader.read_run`).
    """
    try:
        from mcap.reader import make_reader

        with open(path, "rb") as fh:
            reader = make_reader(fh)
            meta = next(
                (dict(m.metadata) for m in reader.iter_metadata() if m.name == METADATA_NAME), None
            )
            attachments = {a.name: bytes(a.data) for a in reader.iter_attachments()}
        if meta is not None:
            return RunHeader(path, meta, attachments)
    except Exception:  # a cut or odd file: the full reader says what is wrong with it
        pass
    log = read_run(path)
    return RunHeader(path, dict(log.meta), dict(log.attachments))


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def check_roles(unloaded: RunHeader, loaded: RunHeader | None) -> None:
    """Refuse the same run given twice, and runs whose metadata contradict their role.

    Raises
    ------
    InputError
        One line naming the files: identical runs, swapped runs, or a run of the other kind
        (only when both runs are given).
    """
    if loaded is None:
        # One run alone fits the dynamic parameters with given gains; a payload it carries is
        # absorbed into the last link's (the run's notes say so).
        return
    a, b = unloaded.path, loaded.path
    same = a.resolve() == b.resolve() or (
        a.stat().st_size == b.stat().st_size and _digest(a) == _digest(b)
    )
    if same:
        raise InputError(
            f"--unloaded {a} and --loaded {b} are the same run: IDIM-WTLS needs one run without "
            "and one with the payload",
            key="--loaded",
        )
    if unloaded.kind == "loaded" and loaded.kind == "unloaded":
        raise InputError(
            f"swapped runs: --unloaded {a} is a loaded run ({unloaded.describe()}) and --loaded "
            f"{b} an unloaded one ({loaded.describe()}); exchange them",
            key="--unloaded",
        )
    if unloaded.kind == "loaded":
        raise InputError(
            f"--unloaded {a} is a loaded run ({unloaded.describe()})", key="--unloaded"
        )
    if loaded.kind == "unloaded":
        raise InputError(f"--loaded {b} is an unloaded run ({loaded.describe()})", key="--loaded")


def attached_payload(header: RunHeader, n_links: int) -> Payload:
    """The payload TOML attached to a loaded log (used when ``--payload`` is not given).

    Raises
    ------
    InputError
        No payload TOML attached (or several), or the attached one is invalid.
    """
    found: list[tuple[str, bytes]] = []
    for name, data in header.attachments.items():
        if not name.lower().endswith(".toml"):
            continue
        try:
            doc = tomllib.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, tomllib.TOMLDecodeError):
            continue
        if isinstance(doc.get("payload"), dict):
            found.append((name, data))
    want = header.meta.get("payload", "")
    if len(found) > 1:
        found = [f for f in found if Path(f[0]).stem == want] or found
    if len(found) != 1:
        what = "no payload TOML" if not found else f"{len(found)} payload TOMLs"
        raise InputError(
            f"{header.path} has {what} attached: give the payload file", key="--payload"
        )
    name, data = found[0]
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / Path(name).name
        p.write_bytes(data)
        try:
            return load_payload(p, n_links)
        except ConfigError as exc:
            raise InputError(
                f"payload {name!r} attached to {header.path}: {exc}", key="--payload"
            ) from None


# --------------------------------------------------------------------------------------------
# Reading a run


@dataclass
class LoadedRun:
    """A run read from its log and made uniform in time (only what identification uses)."""

    label: str
    path: Path
    meta: dict[str, str]
    attachments: dict[str, bytes]
    t0: float
    q: np.ndarray
    current: np.ndarray
    rate_hz: float
    payload: Payload | None
    notes: list[str] = field(default_factory=list)
    time_base: TimeBase | None = None
    channel: str = "reference"
    excitation_start_s: float | None = None


def excitation_start(log: RunLog) -> float | None:
    """When the excitation began on the log's clock ``t`` (s): the first sample at or after the
    session's ``phase excitation`` event; None for a log without one (another program's)."""
    if log.log_time_ns.shape != log.t.shape:
        return None
    for ev in log.events:
        if ev.get("phase") == "excitation":
            k = int(np.searchsorted(log.log_time_ns, int(ev["log_time_ns"])))
            return float(log.t[k]) if k < log.t.size else None
    return None


def load_run(
    path: Path, robot: Robot, label: str, payload: Payload | None, current: str = "reference"
) -> LoadedRun:
    """Read one run log for ``robot``, on a uniform time grid (:mod:`.timebase`).

    ``current``: ``reference`` (the current references, the paper's v_τ) or ``measured``.

    Raises
    ------
    DataError
        Unreadable log, wrong joint count, NaN, non-monotonic time, large gaps, a time base
        disagreeing with ``sync_period_s``, no measured current when it is asked for.
    """
    log = read_run(path, robot.n)
    if current == "measured":
        bad = ~np.isfinite(log.current)
        if bad.any():
            j = int(np.flatnonzero(bad.any(axis=0))[0])
            raise DataError(
                f"--current measured: the log has no measured current of joint "
                f"{log.joint_names[j]} in {int(bad[:, j].sum())} samples",
                file=path,
            )
        chosen = log.current
    else:
        chosen = log.current_reference
    q, v, tb, notes = uniform_samples(
        log.t, log.cycle, log.position, chosen, log.sync_period_s, path=path
    )
    if log.truncated:
        notes.append(f"truncated log: {log.messages_recovered} messages recovered")
    if log.meta.get("robot") not in (None, robot.name):
        notes.append(f"recorded on robot {log.meta.get('robot')!r}, identified as {robot.name!r}")
    logged_payload = log.meta.get("payload", "none")
    if payload is None and logged_payload not in ("none", ""):
        notes.append(f"the log names payload {logged_payload!r} but the run is used unloaded")
    if payload is not None and logged_payload not in (payload.name, "none", ""):
        notes.append(f"the log names payload {logged_payload!r}, the payload file {payload.name!r}")
    unit = log.meta.get("current_unit")
    if unit:
        notes.append(f"currents in {unit}")
    if current == "measured":
        notes.append("measured currents used (--current measured)")
    # The log's other arrays (the other current, set-points, cycles) are not kept: for long
    # runs they are most of the memory.
    return LoadedRun(
        label=label,
        path=path,
        meta=dict(log.meta),
        attachments=dict(log.attachments),
        t0=float(log.t[0]),
        q=q,
        current=v,
        rate_hz=1.0 / tb.period_s,
        payload=payload,
        notes=notes,
        time_base=tb,
        channel=current,
        excitation_start_s=excitation_start(log),
    )
