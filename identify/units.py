"""Units of the identified parameters, for the report tables (revolute joints, SI units).

A regrouped base parameter (``ZZ1R = ZZ1 + Ia1 + YY2 + ...``) has the unit of the standard
parameter it is named after: every regrouping is dimensionally consistent.
"""

from __future__ import annotations

import re

#: Unit of a drive gain, joint side.
GAIN_UNIT = "N·m/A"

_UNITS = (
    ("fvm", "N·m·s/rad"),
    ("fcm", "N·m"),
    ("OFF", "N·m"),
    ("Fv", "N·m·s/rad"),
    ("Fc", "N·m"),
    ("Ia", "kg·m²"),
    ("XX", "kg·m²"),
    ("XY", "kg·m²"),
    ("XZ", "kg·m²"),
    ("YY", "kg·m²"),
    ("YZ", "kg·m²"),
    ("ZZ", "kg·m²"),
    ("MX", "kg·m"),
    ("MY", "kg·m"),
    ("MZ", "kg·m"),
    ("M", "kg"),
)

_NAME = re.compile(r"^([A-Za-z]+?)(\d+)R?$")


def parameter_unit(name: str) -> str:
    """Unit of a standard or base parameter by its name (``ZZ1R``, ``Fv3``, ``fvm6``); ``""``
    when the name is not one of the model's."""
    m = _NAME.match(name)
    kind = m.group(1) if m else name
    for prefix, unit in _UNITS:
        if kind == prefix:
            return unit
    return ""
