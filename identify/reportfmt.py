"""Formatting shared by the report's modules: JSON numbers, short numbers, payload keys."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: Keys of the payload parameters in report.json (contracts §5), by PAYLOAD_PARAMS position.
PAYLOAD_KEYS = ("XX", "XY", "XZ", "YY", "YZ", "ZZ", "MX", "MY", "MZ", "mass")


def json_num(x: float | np.floating[Any] | None) -> float | None:
    """A JSON number (None for NaN/inf, which JSON cannot hold)."""
    if x is None:
        return None
    v = float(x)
    return v if math.isfinite(v) else None


def short(x: float | None, digits: int = 4) -> str:
    """``x`` with ``digits`` significant digits, or an en dash when missing or not finite."""
    if x is None or not math.isfinite(x):
        return "–"
    return f"{x:.{digits}g}"
