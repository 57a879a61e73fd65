"""Small typed accessors for TOML tables that fail with one line naming the file and key."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from drivegain.errors import ConfigError
from drivegain.fileio import reading


def read_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file, turning every failure into a :class:`ConfigError` naming the file."""
    p = Path(path)
    with reading(p, error=ConfigError, expected="a TOML file"), p.open("rb") as fh:
        try:
            return tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"not valid TOML ({exc})", file=p) from None


def read_root(path: str | Path, tables: set[str]) -> Table:
    """The top-level table of a TOML file holding only the ``tables`` named.

    Raises
    ------
    ConfigError
        One line naming the file (unreadable, not TOML) or the unknown key.
    """
    p = Path(path)
    root = Table(read_toml(p), p)
    root.reject_unknown(tables)
    return root


class Table:
    """A TOML table with its file and dotted key path, for precise error messages."""

    def __init__(self, data: Any, file: str | Path, key: str = ""):
        if not isinstance(data, dict):
            raise ConfigError("expected a table", file=file, key=key or None)
        self.data = data
        self.file = str(file)
        self.key = key

    def _k(self, name: str) -> str:
        return f"{self.key}.{name}" if self.key else name

    def error(self, name: str, message: str) -> ConfigError:
        return ConfigError(message, file=self.file, key=self._k(name))

    def has(self, name: str) -> bool:
        return name in self.data

    def raw(self, name: str) -> Any:
        if name not in self.data:
            raise self.error(name, "missing")
        return self.data[name]

    def table(self, name: str) -> Table:
        return Table(self.raw(name), self.file, self._k(name))

    def tables(self, name: str, *, required: bool = True) -> list[Table]:
        if not required and name not in self.data:
            return []
        value = self.raw(name)
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise self.error(name, "expected an array of tables ([[...]])")
        return [Table(v, self.file, f"{self._k(name)}[{i}]") for i, v in enumerate(value)]

    def get_str(self, name: str, default: str | None = None, choices: tuple[str, ...] = ()) -> str:
        if default is not None and name not in self.data:
            return default
        value = self.raw(name)
        if not isinstance(value, str):
            raise self.error(name, f"expected a string, got {type(value).__name__}")
        if choices and value not in choices:
            raise self.error(name, f"must be one of {', '.join(choices)}, got {value!r}")
        return value

    def get_int(self, name: str, default: int | None = None, minimum: int | None = None) -> int:
        if default is not None and name not in self.data:
            return default
        value = self.raw(name)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(name, f"expected an integer, got {value!r}")
        if minimum is not None and value < minimum:
            raise self.error(name, f"must be >= {minimum}, got {value}")
        return value

    def get_float(
        self,
        name: str,
        default: float | None = None,
        *,
        positive: bool = False,
        nonzero: bool = False,
    ) -> float:
        if default is not None and name not in self.data:
            return default
        value = self.raw(name)
        return self._check_float(name, value, positive=positive, nonzero=nonzero)

    def _check_float(self, name: str, value: Any, *, positive: bool, nonzero: bool) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(name, f"expected a number, got {value!r}")
        v = float(value)
        if not math.isfinite(v):
            raise self.error(name, f"must be finite, got {v}")
        if positive and v <= 0.0:
            raise self.error(name, f"must be > 0, got {v}")
        if nonzero and v == 0.0:
            raise self.error(name, "must not be zero")
        return v

    def get_floats(self, name: str, length: int | None = None) -> np.ndarray:
        value = self.raw(name)
        if not isinstance(value, list):
            raise self.error(name, f"expected an array of numbers, got {value!r}")
        if length is not None and len(value) != length:
            raise self.error(name, f"expected {length} values, got {len(value)}")
        out = [self._check_float(name, v, positive=False, nonzero=False) for v in value]
        return np.array(out, dtype=float)

    def get_strs(self, name: str, default: list[str] | None = None) -> list[str]:
        if default is not None and name not in self.data:
            return list(default)
        value = self.raw(name)
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise self.error(name, "expected an array of strings")
        return list(value)

    def reject_unknown(self, allowed: set[str]) -> None:
        """Reject keys that are not in ``allowed`` (catches mistyped keys)."""
        for name in self.data:
            if name not in allowed:
                raise self.error(
                    name, f"unknown key (expected one of {', '.join(sorted(allowed))})"
                )
