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
objects allocated since are collected as usual. Holds nest and may come from several owners
(each :class:`~.realtime.RealtimePolicy` entered for a process: a rig's, the drives' child
process's); the last :func:`release` gives the frozen objects back to the collector
(``gc.unfreeze``). Garbage that existed at a hold is kept until then, unless the first hold
collects first (``hold(collect=True)``, before any drive is supervised). :func:`refreeze` freezes
again while held, after a set-up that lives as long as the hold (a rig's booted master and
simulated drives), so that later collections do not walk it either; it does not collect, as
heartbeats are supervised by then, so what the set-up left as garbage is kept until the last
release (bounded: once per set-up). Never refreeze objects that die before the hold ends (a
run's session): a reference cycle among them would be kept until the last release.
"""

from __future__ import annotations

import gc
import threading

from drivegain.errors import UsageError

_lock = threading.Lock()
_holders = 0


def hold(*, collect: bool = False) -> None:
    """Freeze what the collector tracks now; pair with :func:`release`.

    Parameters
    ----------
    collect
        Run a full collection first if no hold is in force (0.1-0.26 s in a loaded process,
        more than a TPDO time-out: only before any drive is supervised), so that no garbage is
        frozen with the live objects. Under another hold, drives may be supervised: no pause.
    """
    global _holders
    with _lock:
        if collect and _holders == 0:
            gc.collect()
        _holders += 1
        gc.freeze()  # O(1): the generations' lists are spliced, nothing is walked


def refreeze() -> bool:
    """While held, freeze what the collector tracks now as well; else do nothing.

    O(1) and without a collection (drives may be supervised): garbage tracked now is kept until
    the last release, so call it right after a long-lived set-up, not per run.

    Returns
    -------
    bool
        Whether a hold was in force.
    """
    with _lock:
        if _holders == 0:
            return False
        gc.freeze()
        return True


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
            raise UsageError("gcfreeze.release() without a hold")
        _holders -= 1
        if _holders == 0:
            gc.unfreeze()


def holders() -> int:
    """Holds in force (for tests and diagnostics)."""
    with _lock:
        return _holders
