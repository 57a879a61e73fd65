"""Markdown helpers of the study's document: number format, tables, verdict phrases.

The number format and the table layout are those of the identification report
(:mod:`drivegain.identify.report`), so both documents print numbers alike.
"""

from __future__ import annotations

from collections.abc import Sequence

from drivegain.identify.report import _g, _table


def fmt(x: float | None, digits: int = 4) -> str:
    """``x`` with ``digits`` significant digits, or an en dash when missing or not finite."""
    return _g(x, digits)


def table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """Lines of a Markdown table, followed by the blank line that ends it."""
    return [*_table(header, rows), ""]


def ratio_word(r: Sequence[float]) -> str:
    """A paired RMS ratio (this method over ours) ``(ratio, lo, hi)`` with its verdict.

    The verdict is a tie when the 95 % interval ``[lo, hi]`` holds 1.
    """
    ratio, lo, hi = r
    if lo > 1.0:
        return f"{ratio:.3g} [{lo:.3g}, {hi:.3g}]: ours smaller"
    if hi < 1.0:
        return f"{ratio:.3g} [{lo:.3g}, {hi:.3g}]: **this one smaller**"
    return f"{ratio:.3g} [{lo:.3g}, {hi:.3g}]: tie"


def sigma_word(z_std: float) -> str:
    """How a spread of z = (estimate − truth)/σ̂ (dimensionless) judges σ̂."""
    if z_std > 1.03:
        return f"about {100 * (z_std - 1):.0f} % too small (optimistic)"
    if z_std < 0.97:
        return f"about {100 * (1 - z_std):.0f} % too large (conservative)"
    return "right to within 3 %"
