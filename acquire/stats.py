"""Bounded-memory statistics of the cycle loop: timing jitter and per-node TPDO counters.

A run may last hours, so nothing here keeps one value per cycle: timing samples go into a fixed
histogram (1 µs bins) from which quantiles are read at the end.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np


class Histogram:
    """A fixed-width histogram of non-negative durations in nanoseconds.

    Parameters
    ----------
    bin_ns
        Bin width, ns (1 µs by default: finer than any useful jitter figure).
    max_ns
        Values at or above this go to one overflow bin (their exact maximum is still kept).
    """

    def __init__(self, bin_ns: int = 1_000, max_ns: int = 100_000_000):
        self.bin_ns = int(bin_ns)
        self._bins = np.zeros(max_ns // self.bin_ns + 1, dtype=np.int64)
        self.count = 0
        self.total_ns = 0
        self.max_ns = 0

    def add(self, value_ns: int) -> None:
        """Add one duration (negative values count as zero), ns."""
        v = max(int(value_ns), 0)
        self._bins[min(v // self.bin_ns, len(self._bins) - 1)] += 1
        self.count += 1
        self.total_ns += v
        if v > self.max_ns:
            self.max_ns = v

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (0..1), ns, at bin resolution (upper edge of the bin); 0 if empty."""
        if self.count == 0:
            return 0.0
        rank = max(1, int(np.ceil(q * self.count)))
        idx = int(np.searchsorted(np.cumsum(self._bins), rank))
        if idx >= len(self._bins) - 1:
            return float(self.max_ns)
        return float(min((idx + 1) * self.bin_ns, self.max_ns))

    @property
    def mean_ns(self) -> float:
        return self.total_ns / self.count if self.count else 0.0


@dataclass
class LoopStats:
    """Timing and TPDO statistics of one run.

    ``wake_late`` is how late the loop woke after each absolute deadline (realtime only);
    ``sync_dev`` is the deviation of the interval between consecutive SYNCs from the period;
    ``service`` the time from SYNC to the last TPDO of the cycle; ``late_cycles`` the cycles whose
    last TPDO came more than one period after the SYNC. ``late_tpdo`` / ``missing_tpdo`` count,
    per node id, the TPDOs that arrived after their cycle was over or not at all (a missing TPDO
    stops the run, so it is counted once at most). ``wall_s`` is the wall time of the cycle loop
    (``speed`` in the summary: simulated seconds per wall second).
    """

    period_s: float
    clock: str
    cycles: int = 0
    overruns: int = 0
    late_cycles: int = 0
    wall_s: float = 0.0
    wake_late: Histogram = field(default_factory=Histogram)
    sync_dev: Histogram = field(default_factory=Histogram)
    service: Histogram = field(default_factory=Histogram)
    late_tpdo: Counter[int] = field(default_factory=Counter)
    missing_tpdo: Counter[int] = field(default_factory=Counter)

    def summary(self) -> dict[str, Any]:
        """The statistics as strings (for an ``/events`` message and the status reply)."""

        def us(h: Histogram, q: float) -> str:
            return f"{h.quantile(q) / 1e3:.1f}"

        out = {
            "clock": self.clock,
            "period_s": f"{self.period_s:g}",
            "cycles": str(self.cycles),
            "overruns": str(self.overruns),
            "late_cycles": str(self.late_cycles),
            "wall_s": f"{self.wall_s:.3f}",
            "speed": f"{self.cycles * self.period_s / self.wall_s:.3f}" if self.wall_s else "0",
            "sync_jitter_p50_us": us(self.sync_dev, 0.5),
            "sync_jitter_p99_us": us(self.sync_dev, 0.99),
            "sync_jitter_max_us": f"{self.sync_dev.max_ns / 1e3:.1f}",
            "wake_late_p50_us": us(self.wake_late, 0.5),
            "wake_late_p99_us": us(self.wake_late, 0.99),
            "wake_late_max_us": f"{self.wake_late.max_ns / 1e3:.1f}",
            "service_p50_us": us(self.service, 0.5),
            "service_p99_us": us(self.service, 0.99),
            "late_tpdo": _counter_text(self.late_tpdo),
            "missing_tpdo": _counter_text(self.missing_tpdo),
        }
        return out


def _counter_text(c: Counter[int]) -> str:
    """``"3:1,5:2"`` (node:count), or ``"none"``."""
    items = sorted((k, v) for k, v in c.items() if v)
    return ",".join(f"{k}:{v}" for k, v in items) if items else "none"
