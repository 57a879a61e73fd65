"""What a batch identifies: a campaign TOML, or a folder (or glob) of logs, turned into tasks.

A campaign file (locations relative to the file's folder; any fsspec URL works)::

    [batch]
    out = "fleet"                 # results folder or URL (default: beside the file, "fleet")
    threshold = 5.0               # drift flag: |change| / combined σ beyond this
    baseline = "2026-05"          # campaign every other is compared with (default: earliest)
    retries = 2                   # retries of a task on a failure (a dead worker is rescheduled)
    identify_plots = true         # each identification's own PNG plots

    [defaults]                    # any key of a [[campaign.robot]] entry, for all of them
    robot = "tx40"                # robot TOML, or a shipped robot's name
    payload = "payload-4590g.toml"

    [[campaign]]
    name = "2026-05"
    date = 2026-05-04

    [[campaign.robot]]
    id = "cell1-r1"
    unloaded = "2026-05/cell1-r1/a.mcap"
    loaded = "2026-05/cell1-r1/b.mcap"
    # payload, robot, gains ("apriori", a TOML or a report.json) as in `drivegain identify`

A folder or glob of logs instead: ``ROBOT_ID/CAMPAIGN/*.mcap``, each log's metadata saying
which run it is (``unloaded``/``loaded``) and when it started (the campaign's date); the robot
and payload of a robot are ``ROBOT_ID/robot.toml`` and ``ROBOT_ID/payload.toml`` when present,
else the command's ``--robot`` and ``--payload``.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import json
import re
import tomllib
from dataclasses import asdict, dataclass, field

from drivegain.config._toml import Table
from drivegain.errors import ConfigError, DataError, InputError
from drivegain.fleet import storage

#: Robot ids and campaign names become folder names: keep them to a safe alphabet.
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
#: Default drift threshold, in combined standard deviations.
DEFAULT_THRESHOLD = 5.0
DEFAULT_RETRIES = 2
ROBOT_KEYS = {"id", "robot", "unloaded", "loaded", "payload", "gains"}


@dataclass(frozen=True)
class Task:
    """One identification: one robot's runs of one campaign (locations are fsspec strings).

    Attributes
    ----------
    robot_id
        The robot's identifier in the fleet (its folder name in the results).
    campaign, date
        Campaign name and its date (ISO 8601, ``YYYY-MM-DD``).
    robot
        Robot TOML location, or the name of a shipped robot.
    unloaded, loaded, payload
        Run logs and the loaded run's payload TOML (``None`` when absent).
    gains
        ``drivegain identify --gains`` (``None``: identified when a loaded run is given).
    identify_plots
        Whether the identification writes its own PNG plots.
    """

    robot_id: str
    campaign: str
    date: str
    robot: str
    unloaded: str
    loaded: str | None = None
    payload: str | None = None
    gains: str | None = None
    identify_plots: bool = True

    @property
    def key(self) -> str:
        """``CAMPAIGN/ROBOT_ID``: the task's folder in the results and its Dask key stem."""
        return f"{self.campaign}/{self.robot_id}"

    def fingerprint(self) -> str:
        """Hash of everything that decides the result: a result with another one is redone."""
        text = json.dumps(asdict(self), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class BatchOptions:
    """How a batch runs and reports (the ``[batch]`` table and the command's options)."""

    out: str
    threshold: float = DEFAULT_THRESHOLD
    baseline: str | None = None
    retries: int = DEFAULT_RETRIES


@dataclass(frozen=True)
class Batch:
    """The tasks of a batch, its options and where they were read from."""

    tasks: list[Task]
    options: BatchOptions
    source: str
    notes: list[str] = field(default_factory=list)


def _name(t: Table, key: str, what: str) -> str:
    value = t.get_str(key)
    if not NAME.match(value):
        raise t.error(key, f"{what} must be letters, digits, '.', '_' or '-', got {value!r}")
    return value


def _date(t: Table, key: str) -> str:
    value = t.raw(key)
    if isinstance(value, dt.datetime):
        return value.date().isoformat()
    if isinstance(value, dt.date):
        return value.isoformat()
    if isinstance(value, str):
        try:
            return dt.date.fromisoformat(value[:10]).isoformat()
        except ValueError:
            pass
    raise t.error(key, f"expected a date (YYYY-MM-DD), got {value!r}")


def _location(t: Table, key: str, folder: str, default: str | None = None) -> str | None:
    if not t.has(key):
        return None if default is None else default
    return storage.resolve(t.get_str(key), folder)


def _robot(spec: str, folder: str | None) -> str:
    """A robot location, or the shipped robot of that name (a bare name such as ``tx40``)."""
    if "/" not in spec and "." not in spec and "://" not in spec:
        return spec
    return storage.resolve(spec, folder)


def load_campaign(
    location: str, *, out: str | None = None, threshold: float | None = None
) -> Batch:
    """Read a campaign file (module docstring).

    ``out`` and ``threshold`` override the file's ``[batch]`` values.

    Raises
    ------
    ConfigError
        Unreadable TOML, unknown or mistyped key, duplicate robot in a campaign (names the file
        and key).
    """
    raw = storage.read_bytes(location)
    try:
        data = tomllib.load(io.BytesIO(raw))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"not valid TOML ({exc})", file=location) from None
    root = Table(data, location)
    root.reject_unknown({"batch", "defaults", "campaign"})
    folder = storage.parent(location)
    batch = root.table("batch") if root.has("batch") else Table({}, location, "batch")
    batch.reject_unknown({"out", "threshold", "baseline", "retries", "identify_plots"})
    defaults = root.table("defaults") if root.has("defaults") else Table({}, location, "defaults")
    defaults.reject_unknown(ROBOT_KEYS - {"id", "unloaded", "loaded"})
    plots = batch.raw("identify_plots") if batch.has("identify_plots") else True
    if not isinstance(plots, bool):
        raise batch.error("identify_plots", f"expected true or false, got {plots!r}")
    options = BatchOptions(
        out=out or _location(batch, "out", folder, storage.resolve("fleet", folder)) or "fleet",
        threshold=threshold if threshold is not None else _threshold(batch),
        baseline=batch.get_str("baseline") if batch.has("baseline") else None,
        retries=batch.get_int("retries", DEFAULT_RETRIES, minimum=0),
    )
    tasks: list[Task] = []
    names: set[str] = set()
    for c in root.tables("campaign"):
        c.reject_unknown({"name", "date", "robot"})
        name = _name(c, "name", "a campaign name")
        if name in names:
            raise c.error("name", f"campaign {name!r} appears twice")
        names.add(name)
        date = _date(c, "date")
        seen: set[str] = set()
        for r in c.tables("robot"):
            r.reject_unknown(ROBOT_KEYS)
            rid = _name(r, "id", "a robot id")
            if rid in seen:
                raise r.error("id", f"robot {rid!r} appears twice in campaign {name!r}")
            seen.add(rid)
            tasks.append(_task(r, defaults, folder, rid, name, date, plots))
    if options.baseline is not None and options.baseline not in names:
        raise batch.error("baseline", f"no campaign named {options.baseline!r}")
    if not tasks:
        raise root.error("campaign", "no robot to identify")
    return Batch(tasks=tasks, options=options, source=location)


def _threshold(batch: Table) -> float:
    value = batch.get_float("threshold", DEFAULT_THRESHOLD, positive=True)
    return value


def _task(
    r: Table, defaults: Table, folder: str, rid: str, name: str, date: str, plots: bool
) -> Task:
    def pick(key: str) -> str | None:
        if r.has(key):
            return r.get_str(key)
        return defaults.get_str(key) if defaults.has(key) else None

    robot = pick("robot")
    if robot is None:
        raise r.error("robot", "missing (give it here or in [defaults])")
    loaded = _location(r, "loaded", folder)
    payload = pick("payload")
    gains = pick("gains")
    if gains is not None and gains not in ("apriori", "gear-ratios"):
        gains = storage.resolve(gains, folder)
    return Task(
        robot_id=rid,
        campaign=name,
        date=date,
        robot=_robot(robot, folder),
        unloaded=_location(r, "unloaded", folder) or r.get_str("unloaded"),
        loaded=loaded,
        payload=storage.resolve(payload, folder) if payload is not None and loaded else None,
        gains=gains,
        identify_plots=plots,
    )


# --------------------------------------------------------------------------------------------
# A folder or glob of logs


def _log_metadata(location: str) -> dict[str, str]:
    """The ``drivegain.run`` metadata record of a log (contracts §4)."""
    from mcap.reader import make_reader

    fs, path = storage.filesystem(location)
    try:
        with fs.open(path, "rb") as fh:
            for record in make_reader(fh).iter_metadata():
                if record.name == "drivegain.run":
                    return dict(record.metadata)
    except Exception as exc:  # the mcap reader raises its own error types
        raise DataError(f"not a readable MCAP log ({exc})", file=location) from None
    raise DataError("no drivegain.run metadata record", file=location)


def load_logs(
    pattern: str,
    *,
    out: str,
    robot: str | None,
    payload: str | None,
    threshold: float = DEFAULT_THRESHOLD,
    baseline: str | None = None,
    retries: int = DEFAULT_RETRIES,
) -> Batch:
    """Tasks from a folder (every ``*.mcap`` below it) or a glob of logs (module docstring).

    Raises
    ------
    InputError
        No log found, a log that is neither run, two logs of one run, no robot file.
    """
    magic = any(ch in pattern for ch in "*?[")
    files = storage.glob(pattern) if magic else storage.listing(pattern, ".mcap")
    files = [f for f in files if f.endswith(".mcap")]
    if not files:
        raise InputError("no .mcap log found", file=pattern)
    groups: dict[tuple[str, str], dict[str, str]] = {}
    dates: dict[tuple[str, str], str] = {}
    for f in files:
        parts = f.rstrip("/").split("/")
        if len(parts) < 3:
            raise InputError("expected ROBOT_ID/CAMPAIGN/NAME.mcap", file=f)
        rid, campaign = parts[-3], parts[-2]
        for what, value in (("robot id", rid), ("campaign", campaign)):
            if not NAME.match(value):
                raise InputError(f"{what} folder name {value!r} is not usable", file=f)
        meta = _log_metadata(f)
        run = meta.get("run", "")
        if run not in ("unloaded", "loaded"):
            raise DataError(f"run {run!r} is neither unloaded nor loaded", file=f, key="run")
        group = groups.setdefault((rid, campaign), {})
        if run in group:
            raise DataError(f"a second {run} run (first: {group[run]})", file=f, key="run")
        group[run] = f
        if run == "unloaded":
            dates[(rid, campaign)] = meta.get("started_at", "")[:10]
    tasks = []
    for (rid, campaign), runs in sorted(groups.items()):
        if "unloaded" not in runs:
            raise InputError(f"robot {rid}, campaign {campaign}: no unloaded run", file=pattern)
        robot_dir = storage.parent(storage.parent(runs["unloaded"]))
        own_robot = storage.join(robot_dir, "robot.toml")
        own_payload = storage.join(robot_dir, "payload.toml")
        rob = own_robot if storage.exists(own_robot) else robot
        if rob is None:
            raise InputError(f"robot {rid}: no robot.toml beside its logs", key="--robot")
        pay = own_payload if storage.exists(own_payload) else payload
        if "loaded" in runs and pay is None:
            raise InputError(f"robot {rid}: no payload.toml beside its logs", key="--payload")
        try:
            date = dt.date.fromisoformat(dates[(rid, campaign)]).isoformat()
        except ValueError:
            raise DataError(
                "started_at is not an ISO 8601 date", file=runs["unloaded"], key="started_at"
            ) from None
        tasks.append(
            Task(
                robot_id=rid,
                campaign=campaign,
                date=date,
                robot=_robot(rob, None),
                unloaded=runs["unloaded"],
                loaded=runs.get("loaded"),
                payload=pay if "loaded" in runs else None,
            )
        )
    options = BatchOptions(out=out, threshold=threshold, baseline=baseline, retries=retries)
    return Batch(tasks=tasks, options=options, source=pattern)


def load_batch(
    source: str,
    *,
    out: str | None = None,
    robot: str | None = None,
    payload: str | None = None,
    threshold: float | None = None,
    baseline: str | None = None,
    retries: int | None = None,
) -> Batch:
    """A campaign file (``*.toml``) or a folder/glob of logs; command-line values win."""
    if source.endswith(".toml"):
        b = load_campaign(source, out=out, threshold=threshold)
        opts = b.options
        if baseline is not None or retries is not None:
            opts = BatchOptions(
                out=opts.out,
                threshold=opts.threshold,
                baseline=baseline if baseline is not None else opts.baseline,
                retries=retries if retries is not None else opts.retries,
            )
        return Batch(tasks=b.tasks, options=opts, source=b.source)
    if out is None:
        raise InputError("a folder of logs needs the results location", key="--out")
    return load_logs(
        source,
        out=out,
        robot=robot,
        payload=payload,
        threshold=DEFAULT_THRESHOLD if threshold is None else threshold,
        baseline=baseline,
        retries=DEFAULT_RETRIES if retries is None else retries,
    )


def robot_location(spec: str) -> str:
    """A task's robot as a location: shipped robots are resolved to their packaged TOML."""
    if "/" in spec or "." in spec or "://" in spec:
        return spec
    from drivegain.config import resource_path

    try:
        return str(resource_path(f"{spec}.toml"))
    except FileNotFoundError:
        raise InputError(f"no shipped robot named {spec!r}", key="robot") from None


__all__ = ["Batch", "BatchOptions", "Task", "load_batch", "load_campaign", "load_logs"]
