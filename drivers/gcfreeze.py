"""Keep the garbage collector's pauses short while drives are supervised.

A full collection of CPython's cyclic garbage collector walks every object it tracks, in
whichever thread happens to trigger it and holding the interpreter lock meanwhile: the cycle
thread, the bus reader that collects the TPDOs, the simulated drives. A process that has imported
numpy, scipy, Pinocchio and canopen tracks a few hundred thousand objects; in the test suite on
a shared 2-core machine, full collections took 0.1-0.26 s (measured with ``gc.callbacks``), which
is longer than a TPDO time-out and most of a heartbeat time-out. Such a pause once stopped a
lockstep stream with "TPDO1 of cycle 926 missing 0.2 s after SYNC".

While held, everything the collector tracked at the time of a :func:`hold` is moved into its
permanent generation (``gc.freeze``): later collections walk only what was allocated since, and
objects allocated since are collected as usual. Holds nest and may come from several masters;
the last :func:`release` gives the frozen objects back to the collector (``gc.unfreeze``).
Garbage that existed at a hold is kept until then: it is bounded by what the set-up left.
"""

from __future__ import annotations

import gc
import threading

_lock = threading.Lock()
_holders = 0


def hold() -> None:
    """Freeze what the collector tracks now; pair with :func:`release`."""
    global _holders
    with _lock:
        _holders += 1
        gc.freeze()  # O(1): the generations' lists are spliced, nothing is walked


def release() -> None:
    """End one hold; the last one unfreezes.

    Raises
    ------
    RuntimeError
        More releases than holds.
    """
    global _holders
    with _lock:
        if _holders == 0:
            raise RuntimeError("gcfreeze.release() without a hold")
        _holders -= 1
        if _holders == 0:
            gc.unfreeze()


def holders() -> int:
    """Holds in force (for tests and diagnostics)."""
    with _lock:
        return _holders
