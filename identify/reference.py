"""Published base-parameter values to compare with (e.g. FIGAROH's TX-40 results).

The file is a CSV without header, one base parameter per row: its regrouping expression in
Pinocchio/FIGAROH names (``Izz1 + 1.0*Ia1 + 0.07*mz3``, ``fv1``, ``fsm6`` ...), then one or more
``value, %σ`` pairs (for FIGAROH: OLS then WLS). Each expression is turned into coefficients on
our standard parameters and matched to the base parameter with the same regrouping, so only
like is compared with like.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivegain.dynamics.base import BaseParameters
from drivegain.errors import DataError

#: Pinocchio/FIGAROH parameter stems -> ours.
_STEMS = {
    "Ixx": "XX",
    "Ixy": "XY",
    "Ixz": "XZ",
    "Iyy": "YY",
    "Iyz": "YZ",
    "Izz": "ZZ",
    "mx": "MX",
    "my": "MY",
    "mz": "MZ",
    "m": "M",
    "Ia": "Ia",
    "fv": "Fv",
    "fs": "Fc",
    "off": "OFF",
    # Coupled motor: its rotor inertia seen through the coupling columns, viscous, Coulomb.
    "Iam": "Ia",
    "fvm": "fvm",
    "fsm": "fcm",
}
_TERM = re.compile(r"^\s*(?:([0-9.eE+-]+)\s*\*\s*)?([A-Za-z]+)(\d+)\s*$")


@dataclass(frozen=True)
class ReferenceValue:
    """One published base parameter.

    Attributes
    ----------
    expression
        As published.
    values, rel_std_percent
        Published values and %σ, one per estimator column (None when absent).
    coefficients
        Our standard parameter name -> coefficient.
    """

    expression: str
    values: tuple[float, ...]
    rel_std_percent: tuple[float | None, ...]
    coefficients: dict[str, float]


def parse_expression(text: str, where: str) -> dict[str, float]:
    """``Izz1 + 1.0*Ia1 - 0.225*mz3`` -> ``{"ZZ1": 1, "Ia1": 1, "MZ3": -0.225}``."""
    coef: dict[str, float] = {}
    # Split on + and - that are not part of a number's exponent.
    parts = re.split(r"(?<![eE])\s*([+-])\s*", " " + text.strip())
    sign = 1.0
    for part in parts:
        if part in ("+", "-"):
            sign = 1.0 if part == "+" else -1.0
            continue
        if not part.strip():
            continue
        m = _TERM.match(part)
        if m is None or m.group(2) not in _STEMS:
            raise DataError(f"cannot read the parameter expression {text!r}", file=where)
        c = float(m.group(1)) if m.group(1) else 1.0
        name = f"{_STEMS[m.group(2)]}{m.group(3)}"
        coef[name] = coef.get(name, 0.0) + sign * c
        sign = 1.0
    return coef


def read_reference(path: str | Path) -> list[ReferenceValue]:
    """Read a published base-parameter CSV (see the module docstring).

    Raises
    ------
    DataError
        File missing or unreadable, a row without values, an unknown parameter name.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DataError("file not found", file=p) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot read: {exc}", file=p) from None
    out = []
    for i, row in enumerate(csv.reader(text.splitlines()), start=1):
        if not row or not row[0].strip():
            continue
        where = f"{p}:{i}"
        nums = row[1:]
        if len(nums) < 1:
            raise DataError("expected an expression then values", file=where)
        try:
            floats = [float(v) for v in nums]
        except ValueError:
            raise DataError(f"non-numeric value in {nums}", file=where) from None
        values = tuple(floats[0::2])
        rsd = tuple(floats[1::2]) + (None,) * (len(values) - len(floats[1::2]))
        out.append(
            ReferenceValue(
                expression=row[0].strip(),
                values=values,
                rel_std_percent=rsd,
                coefficients=parse_expression(row[0], where),
            )
        )
    if not out:
        raise DataError("no parameters found", file=p)
    return out


def match_reference(bp: BaseParameters, refs: list[ReferenceValue]) -> list[int | None]:
    """For each reference, the index of our base parameter with the same regrouping, or None.

    Two expressions match when their coefficient vectors over the standard parameters agree to
    1e-3 (published coefficients are rounded) after scaling by the leading coefficient.
    """
    b = bp.matrix()
    names = bp.standard_names
    pos = {nm: i for i, nm in enumerate(names)}
    out: list[int | None] = []
    for ref in refs:
        vec = np.zeros(len(names))
        unknown = False
        for nm, c in ref.coefficients.items():
            if nm not in pos:
                unknown = True
                break
            vec[pos[nm]] = c
        if unknown or not np.any(vec):
            out.append(None)
            continue
        found = None
        for i in range(b.shape[0]):
            row = b[i]
            if np.allclose(row, vec, rtol=1e-3, atol=1e-3 * float(np.abs(vec).max())):
                found = i
                break
        out.append(found)
    return out


def relative_difference(ours: float, theirs: float) -> float:
    """(ours − theirs)/|theirs|, NaN when theirs is 0."""
    return (ours - theirs) / abs(theirs) if theirs != 0 else math.nan
