"""The time base of a recorded run: the ``t`` stamps checked, and made uniform when they are not.

The filters and differences of :mod:`drivegain.identify.prepare` need samples equally spaced in
time. A drivegain log has ``t = cycle · sync_period_s`` exactly; a recording from another
program may not (a controller logging at "100 Hz" every 10 or 12 ms). The ``t`` field is the
authoritative time of each sample (contracts §4), so:

1. The mean step per cycle, ``(t[-1] − t[0]) / (cycle[-1] − cycle[0])``, must agree with the
   declared ``sync_period_s`` to :data:`PERIOD_TOLERANCE`; otherwise the run is refused (one of
   the two is wrong, and guessing which moves the gains by the ratio of the two).
2. When every stamp lies within :data:`JITTER_TOLERANCE` of a period of its cycle's slot, the
   time base counts as uniform: the samples are used as they are (missing cycles, if few, are
   filled by interpolation).
3. Otherwise the time base is irregular: positions are resampled onto a uniform grid at the mean
   step with a cubic spline through the real stamps (it keeps velocities and accelerations
   continuous), the currents likewise. The spread of the steps is reported.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline

from drivegain.errors import DataError

#: Largest relative difference between the declared period and the stamps' mean step.
PERIOD_TOLERANCE = 0.01
#: Largest deviation of a stamp from its uniform slot, as a fraction of the period, for the
#: time base to count as uniform.
JITTER_TOLERANCE = 0.01
#: Largest share of missing SYNC cycles that is filled by interpolation (more is an error).
MAX_MISSING_FRACTION = 0.01
#: Longest gap (in periods) that is filled by interpolation.
MAX_GAP_CYCLES = 10


@dataclass(frozen=True)
class TimeBase:
    """What the stamps of a run say about its sampling.

    Attributes
    ----------
    declared_period_s
        ``sync_period_s`` of the metadata, s.
    period_s
        Mean step per cycle from the stamps, s (the period used).
    min_step_s, max_step_s
        Smallest and largest step between consecutive samples, s.
    spread
        RMS deviation of the steps from their mean, relative to the mean (0 for a uniform base).
    max_jitter
        Largest deviation of a stamp from its uniform slot, in periods.
    uniform
        Whether the stamps are uniform to :data:`JITTER_TOLERANCE`.
    """

    declared_period_s: float
    period_s: float
    min_step_s: float
    max_step_s: float
    spread: float
    max_jitter: float
    uniform: bool

    def note(self) -> str:
        """One line for the report on an irregular time base."""
        return (
            f"irregular time stamps: steps {1e3 * self.min_step_s:.4g}–"
            f"{1e3 * self.max_step_s:.4g} ms (mean {1e3 * self.period_s:.4g} ms, RMS spread "
            f"{100 * self.spread:.3g} %); resampled onto a uniform {1e3 * self.period_s:.4g} ms "
            "grid"
        )

    def as_dict(self) -> dict[str, float | bool]:
        """The fields for ``report.json`` (s, or fractions)."""
        return {
            "declared_period_s": self.declared_period_s,
            "period_s": self.period_s,
            "min_step_s": self.min_step_s,
            "max_step_s": self.max_step_s,
            "spread": self.spread,
            "max_jitter_periods": self.max_jitter,
            "uniform": self.uniform,
        }


def analyse_time_base(
    t: np.ndarray, cycle: np.ndarray, declared_period_s: float, *, path: Path | str | None = None
) -> TimeBase:
    """Check the stamps ``t`` (s) against the cycles and the declared period (s).

    Raises
    ------
    DataError
        Fewer than two samples, or the declared period and the stamps' mean step differ by more
        than :data:`PERIOD_TOLERANCE`.
    """
    t = np.asarray(t, dtype=float)
    cycle = np.asarray(cycle, dtype=np.int64)
    if t.size < 2:
        raise DataError("fewer than two samples", file=path)
    span = int(cycle[-1] - cycle[0])
    if span <= 0:
        raise DataError("the cycle counter does not advance", file=path)
    period = float(t[-1] - t[0]) / span
    diff = period / declared_period_s - 1.0
    if abs(diff) > PERIOD_TOLERANCE:
        raise DataError(
            f"the time stamps step by {1e3 * period:.6g} ms per cycle on average but "
            f"sync_period_s declares {1e3 * declared_period_s:.6g} ms ({100 * diff:+.3g} %, "
            f"tolerance {100 * PERIOD_TOLERANCE:.3g} %): fix the metadata or the stamps",
            file=path,
        )
    slots = t[0] + (cycle - cycle[0]) * period
    jitter = float(np.max(np.abs(t - slots))) / period
    steps = np.diff(t) / np.diff(cycle)
    return TimeBase(
        declared_period_s=float(declared_period_s),
        period_s=period,
        min_step_s=float(steps.min()),
        max_step_s=float(steps.max()),
        spread=float(np.std(steps) / period),
        max_jitter=jitter,
        uniform=jitter <= JITTER_TOLERANCE,
    )


def uniform_samples(
    t: np.ndarray,
    cycle: np.ndarray,
    q: np.ndarray,
    current: np.ndarray,
    declared_period_s: float,
    *,
    path: Path | str | None = None,
) -> tuple[np.ndarray, np.ndarray, TimeBase, list[str]]:
    """Positions (rad) and currents on a uniform time grid.

    Parameters
    ----------
    t
        Stamps, s, (N,), strictly increasing.
    cycle
        SYNC cycle indices, (N,), strictly increasing.
    q
        Joint positions, rad, (N, n).
    current
        Currents, (N, n).
    declared_period_s
        ``sync_period_s`` of the metadata, s.
    path
        The log, for messages.

    Returns
    -------
    q, current, time_base, notes
        Uniformly sampled arrays (period ``time_base.period_s``) and notes for the report.

    Raises
    ------
    DataError
        Period disagreement (:func:`analyse_time_base`), or gaps too many or too long to fill.
    """
    tb = analyse_time_base(t, cycle, declared_period_s, path=path)
    if tb.uniform:
        position = (cycle - cycle[0]).astype(float)
        total = int(cycle[-1] - cycle[0]) + 1
        missing = total - cycle.size
        if missing == 0:
            return q, current, tb, []
        gap = int(np.max(np.diff(cycle))) - 1
    else:
        position = (t - t[0]) / tb.period_s
        total = int(np.floor(position[-1] + 1e-9)) + 1
        missing = max(0, total - t.size)
        gap = int(np.ceil(np.max(np.diff(position)) - 1e-9)) - 1
    if missing > MAX_MISSING_FRACTION * total or gap > MAX_GAP_CYCLES:
        raise DataError(
            f"{missing} of {total} samples are missing (longest gap {gap} periods): too many to "
            "interpolate",
            file=path,
        )
    grid = np.arange(total, dtype=float)
    if tb.uniform:
        qu = np.column_stack([np.interp(grid, position, c) for c in q.T])
        vu = np.column_stack([np.interp(grid, position, c) for c in current.T])
        return qu, vu, tb, [f"{missing} missing SYNC cycles filled by linear interpolation"]
    # Linear interpolation would shrink a harmonic of angular frequency ω by up to (ωh)²/8
    # between stamps, differently on positions and currents; the spline's error is O(h⁴).
    qu = CubicSpline(position, q, axis=0)(grid)
    vu = CubicSpline(position, current, axis=0)(grid)
    return qu, vu, tb, [tb.note()]
