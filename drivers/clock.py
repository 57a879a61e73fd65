"""Which clock paces a run: the simulated one (lockstep) or the wall clock (realtime)."""

from __future__ import annotations

from enum import StrEnum


class Clock(StrEnum):
    """How time advances in a run.

    ``LOCKSTEP``: the simulated drives advance exactly one period per SYNC and the master sends
    the next SYNC as soon as the cycle's TPDOs are in; every supervision time-out counts
    simulated time, so a run is deterministic on a busy machine. ``REALTIME``: SYNC follows the
    wall clock, as on hardware (and always with real drives).
    """

    LOCKSTEP = "lockstep"
    REALTIME = "realtime"
