"""Declarative configuration tables: each TOML table is declared once, as one frozen dataclass.

Every field that is a TOML key carries, besides its type and default, the metadata made by
:func:`setting`: unit, bounds or choices and a one-line doc; choices are enums
(:class:`enum.StrEnum`). Fields the caller computes (a loaded robot, the file name, ...) carry
:func:`derived` instead.
:func:`load_table` builds the dataclass from a :class:`~drivegain.config._toml.Table`: it rejects
unknown keys, reads each key by its declared type, checks the bounds and raises the project's
one-line :class:`~drivegain.errors.ConfigError` naming the file and the key at fault.

Types read from TOML: ``bool``, ``int``, ``float``, ``str``, an enum, :class:`~pathlib.Path`
(see :class:`PathRule`), ``tuple[float, ...]`` / :class:`numpy.ndarray` (arrays of numbers),
``tuple[str, ...]``, ``dict[str, Any]`` (a sub-table kept as is), another table dataclass (a
sub-table), ``tuple[TableClass, ...]`` (an array of tables), each optionally ``| None``.
Anything else takes a ``parse`` function. Cross-field rules live in the dataclass's
``__post_init__``, which raises :class:`SettingError` naming the field.

Example::

    @dataclass(frozen=True)
    class Example:
        period_s: float = field(default=0.004, metadata=setting(unit="s", gt=0.0, doc="period"))

    cfg = load_table(Example, table)
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Callable, Iterable
from enum import Enum, StrEnum
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from drivegain.config._toml import Table

T = TypeVar("T")

#: Key of the :class:`Setting` in a dataclass field's metadata.
SETTING = "drivegain.setting"


class PathRule(StrEnum):
    """How a path setting is resolved.

    ``AS_GIVEN``: a runtime location, kept as written (relative to the working directory);
    ``EXISTING``: a file relative to the TOML file's folder, which must exist;
    ``EXISTING_OR_SHIPPED``: the same, else a file shipped with drivegain (e.g.
    ``"payloads/calibrated-4590g.toml"``).
    """

    AS_GIVEN = "as_given"
    EXISTING = "existing"
    EXISTING_OR_SHIPPED = "existing_or_shipped"


class SettingError(ValueError):
    """An impossible value found by a table's ``__post_init__`` or a ``check``.

    Parameters
    ----------
    key
        The field at fault (its name, or a dotted key relative to the field for a ``check``).
    message
        The reason, one line.
    """

    def __init__(self, key: str, message: str):
        super().__init__(f"{key}: {message}")
        self.key = key
        self.message = message


@dataclasses.dataclass(frozen=True)
class Setting:
    """What a table field declares besides its type and default (see :func:`setting`)."""

    doc: str
    unit: str = ""
    key: str | None = None
    gt: float | None = None
    ge: float | None = None
    le: float | None = None
    magnitude: float | None = None
    nonzero: bool = False
    choices: tuple[Any, ...] = ()
    message: str | None = None
    length: int | None = None
    path: PathRule = PathRule.AS_GIVEN
    parse: Callable[[Table, str], Any] | None = None
    check: Callable[[Any], str | None] | None = None
    derived: bool = False


def setting(
    *,
    doc: str,
    unit: str = "",
    key: str | None = None,
    gt: float | None = None,
    ge: float | None = None,
    le: float | None = None,
    magnitude: float | None = None,
    nonzero: bool = False,
    choices: Iterable[Any] = (),
    message: str | None = None,
    length: int | None = None,
    path: PathRule = PathRule.AS_GIVEN,
    parse: Callable[[Table, str], Any] | None = None,
    check: Callable[[Any], str | None] | None = None,
) -> dict[str, Setting]:
    """Metadata of a field read from a TOML key: ``field(default=..., metadata=setting(...))``.

    The default (``default`` or ``default_factory`` of :func:`dataclasses.field`; neither: the
    key is required) stays with the field, so type checkers see it.

    Parameters
    ----------
    doc, unit
        One line saying what the value is, and its unit (SI, ``rad``; empty if none).
    key
        The TOML key, when it differs from the field name.
    gt, ge, le
        Bounds of a number: ``> gt``, ``>= ge``, ``<= le``.
    magnitude
        Physical bound of a number or of every element of an array: finite and
        ``|value| <= magnitude`` (a typo such as 1e300 is refused at load, not met as an
        overflow in the physics or the numerics).
    nonzero
        A number that must not be zero.
    choices
        Allowed values (enums need none: their members are the choices).
    message
        Replaces the text of a ``ge`` / ``le`` / ``choices`` violation; ``{value}`` is the value,
        ``{bound}`` the bound.
    length
        Required length of an array.
    path
        How a :class:`~pathlib.Path` is resolved (:class:`PathRule`).
    parse
        ``parse(table, key)`` reads a value of a type :func:`load_table` does not know.
    check
        ``check(value)`` returns why a read value is wrong, or ``None``; it may raise
        :class:`SettingError` with a key relative to this one.
    """
    spec = Setting(
        doc=doc,
        unit=unit,
        key=key,
        gt=gt,
        ge=ge,
        le=le,
        magnitude=magnitude,
        nonzero=nonzero,
        choices=tuple(choices),
        message=message,
        length=length,
        path=path,
        parse=parse,
        check=check,
    )
    return {SETTING: spec}


def derived(*, doc: str) -> dict[str, Setting]:
    """Metadata of a table field that is not a TOML key: the loader's caller provides it."""
    return {SETTING: Setting(doc=doc, derived=True)}


@dataclasses.dataclass(frozen=True)
class Declared:
    """One declared field of a table: its dataclass field, resolved type and :class:`Setting`."""

    field: dataclasses.Field[Any]
    type: Any
    spec: Setting

    @property
    def name(self) -> str:
        return self.field.name

    @property
    def key(self) -> str:
        """The TOML key."""
        return self.spec.key or self.field.name

    @property
    def required(self) -> bool:
        return (
            self.field.default is dataclasses.MISSING
            and self.field.default_factory is dataclasses.MISSING
        )

    def default(self) -> Any:
        """The declared default (``dataclasses.MISSING`` if the key is required)."""
        if self.field.default_factory is not dataclasses.MISSING:
            return self.field.default_factory()
        return self.field.default


def declared(cls: type) -> list[Declared]:
    """The fields of the table dataclass ``cls`` declared with :func:`setting` / :func:`derived`."""
    hints = typing.get_type_hints(cls)
    return [
        Declared(f, hints[f.name], f.metadata[SETTING])
        for f in dataclasses.fields(cls)
        if SETTING in f.metadata
    ]


def keys_of(cls: type) -> set[str]:
    """The TOML keys of the table dataclass ``cls``."""
    return {d.key for d in declared(cls) if not d.spec.derived}


def default_of(cls: type, name: str) -> Any:
    """The declared default of field ``name`` of the table dataclass ``cls``."""
    for d in declared(cls):
        if d.name == name:
            return d.default()
    raise KeyError(f"{cls.__name__} declares no setting {name!r}")


def describe(cls: type) -> list[str]:
    """One line per TOML key of ``cls``: key, default, unit and doc (for help and documentation)."""
    lines = []
    for d in declared(cls):
        if d.spec.derived:
            continue
        default = "required" if d.required else f"default {d.default()!r}"
        unit = f", {d.spec.unit}" if d.spec.unit else ""
        lines.append(f"{d.key} ({default}{unit}): {d.spec.doc}")
    return lines


def load_table(
    cls: type[T],
    table: Table,
    *,
    base_dir: Path | None = None,
    also: Iterable[str] = (),
    **given: Any,
) -> T:
    """Build the table dataclass ``cls`` from a TOML table.

    Parameters
    ----------
    cls
        A frozen dataclass whose TOML fields are declared with :func:`setting`.
    table
        The TOML table (with its file and key, for the messages).
    base_dir
        Folder relative file paths are resolved against; default the TOML file's folder.
    also
        Further keys allowed in the table (read by the caller).
    **given
        Values of the :func:`derived` fields (and of settings the caller decides).

    Raises
    ------
    ConfigError
        One line naming the file and the key at fault: an unknown key, a missing required
        key, a wrong type, a value out of bounds or a rule of ``cls`` broken.
    """
    fields = declared(cls)
    table.reject_unknown(keys_of(cls) | set(also))
    values = dict(given)
    key_of = {d.name: d.key for d in fields}
    for d in fields:
        if d.spec.derived or d.name in given:
            continue
        if not table.has(d.key):
            if d.required:
                table.raw(d.key)  # raises "missing"
            continue
        values[d.name] = _read(table, d, base_dir)
    try:
        return cls(**values)
    except SettingError as exc:
        raise table.error(key_of.get(exc.key, exc.key), exc.message) from None


# --- reading one value ------------------------------------------------------------------------


def _read(table: Table, d: Declared, base_dir: Path | None) -> Any:
    spec = d.spec
    value = spec.parse(table, d.key) if spec.parse is not None else _typed(table, d, base_dir)
    _check_bounds(table, d.key, value, spec)
    if spec.check is not None:
        try:
            why = spec.check(value)
        except SettingError as exc:
            raise table.error(f"{d.key}.{exc.key}", exc.message) from None
        if why is not None:
            raise table.error(d.key, why)
    return value


def _strip_none(tp: Any) -> Any:
    if isinstance(tp, types.UnionType) or typing.get_origin(tp) is typing.Union:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return tp


def _typed(table: Table, d: Declared, base_dir: Path | None) -> Any:
    tp = _strip_none(d.type)
    key = d.key
    origin = typing.get_origin(tp)
    if tp is bool:
        value = table.raw(key)
        if not isinstance(value, bool):
            raise table.error(key, f"expected true or false, got {value!r}")
        return value
    if isinstance(tp, type) and issubclass(tp, Enum):
        return tp(table.get_str(key, choices=tuple(str(m.value) for m in tp)))
    if tp is str:
        return table.get_str(key)
    if tp is int:
        return table.get_int(key)
    if tp is float:
        return table.get_float(key)
    if tp is Path:
        return _path(table, key, d.spec.path, base_dir)
    if tp is np.ndarray:
        return _floats(table, d)
    if origin is tuple:
        args = typing.get_args(tp)
        item = args[0]
        if item is float:
            return tuple(float(v) for v in _floats(table, d))
        if item is str:
            return tuple(table.get_strs(key))
        if dataclasses.is_dataclass(item):
            return tuple(
                load_table(item, t, base_dir=base_dir)  # type: ignore[arg-type]
                for t in table.tables(key)
            )
    if tp is dict or origin is dict:
        return dict(table.table(key).data)
    if dataclasses.is_dataclass(tp):
        return load_table(tp, table.table(key), base_dir=base_dir)  # type: ignore[arg-type]
    raise TypeError(f"no TOML reader for {d.type!r} (field {d.name}): declare a parse function")


def _floats(table: Table, d: Declared) -> np.ndarray:
    values = table.get_floats(d.key, length=d.spec.length)
    if d.spec.nonzero and np.any(values == 0.0):
        raise table.error(d.key, "must not be zero")
    return values


def _path(table: Table, key: str, rule: PathRule, base_dir: Path | None) -> Path:
    name = table.get_str(key)
    if rule is PathRule.AS_GIVEN:
        return Path(name)
    p = Path(name)
    if not p.is_absolute():
        p = (base_dir if base_dir is not None else Path(table.file).resolve().parent) / p
    if p.is_file():
        return p
    if rule is PathRule.EXISTING_OR_SHIPPED:
        from drivegain.config import resource_path  # the package imports the loaders

        try:
            return resource_path(name)
        except FileNotFoundError:
            pass
    raise table.error(key, f"file not found: {p}")


def _check_bounds(table: Table, key: str, value: Any, spec: Setting) -> None:
    is_number = isinstance(value, int | float) and not isinstance(value, bool)
    if spec.magnitude is not None and value is not None:
        values = np.atleast_1d(np.asarray(value, dtype=float))
        beyond = ~(np.abs(values) <= spec.magnitude)  # NaN counts as beyond
        if beyond.any():
            bad = values[beyond][0]
            unit = f" {spec.unit}" if spec.unit else ""
            raise table.error(
                key, f"must be finite and within ±{spec.magnitude:g}{unit}, got {bad:g}"
            )
    if is_number:
        if spec.nonzero and value == 0:
            raise table.error(key, "must not be zero")
        if spec.gt is not None and not value > spec.gt:
            raise table.error(key, f"must be > {spec.gt:g}, got {value}")
        for bound, broken, text in (
            (spec.ge, lambda b: value < b, "must be >= {bound:g}, got {value}"),
            (spec.le, lambda b: value > b, "must be <= {bound:g}, got {value}"),
        ):
            if bound is not None and broken(bound):
                template = spec.message or text
                raise table.error(key, template.format(bound=bound, value=value))
    if spec.choices and value not in spec.choices:
        if spec.message:
            raise table.error(key, spec.message.format(value=value))
        allowed = ", ".join(str(c) for c in spec.choices)
        raise table.error(key, f"must be one of {allowed}, got {value!r}")
