"""Markdown helpers of the study's document: number format, tables, verdict phrases, the
scenario table's cells on how the seeds were prepared.

The number format and the table layout are those of the identification report
(:mod:`drivegain.identify.report`), so both documents print numbers alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

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


#: The scenario table's columns on how the seeds were prepared and fitted.
PREPARATION_HEADER = ("Coulomb sign at the position cut-off", "ours' Case 2 left entries out")


def preparation_cells(prep: dict[str, Any] | None) -> list[str]:
    """The scenario table's :data:`PREPARATION_HEADER` cells from a scenario's
    ``preparation`` summary; a dash for a study run before it was recorded."""
    if prep is None:
        return ["–", "–"]
    at = prep["sign_at_position"]
    cutoffs = prep["sign_cutoff_hz"]
    sign = "exact derivatives" if at is None else f"{100 * at:.0f} % of seeds"
    if cutoffs:
        sign += " (" + ", ".join(f"{hz:g}" for hz in cutoffs) + " Hz)"
    seeds, median = prep["case2_left_out_seeds"], prep["case2_left_out_median"]
    left = "–" if seeds is None else f"{100 * seeds:.0f} % of seeds"
    if median is not None:
        left += f" ({100 * median:.0f} % of entries, median)"
    return [sign, left]


def scenario_table(
    rows: Sequence[Sequence[str]], preps: Sequence[dict[str, Any] | None]
) -> list[str]:
    """Lines of the scenario table: each row (scenario, seeds, noise) with its scenario's
    :func:`preparation_cells`."""
    header = ["scenario", "seeds", "noise", *PREPARATION_HEADER]
    return table(header, [[*r, *preparation_cells(p)] for r, p in zip(rows, preps, strict=True)])
