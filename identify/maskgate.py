"""``identify --reversal-mask auto``: the reversal mask on the drives that stick, and only there.

A drive in closed loop stops at each reversal and catches up after it; the fit's κ̂ (the
variance its entries near reversals add, relative to the others', :mod:`.ml`) is what shows it.
On the study's exact-tracking runs (seeds 0-5 of four scenarios) κ̂ stays below 0.6 but on one
of the 12 random excitations (2.1 on j1, 4.7 on j3); on its closed-loop drives it is 1.7-3.9
(optimised excitation) and 2.5-12.5 (random) on every drive (docs/model.md, "Weighting the
reversals out before the decimation"). Where nothing sticks the mask only discards data, so the
gate masks the coupled groups of the drives whose κ̂ reaches Case 2's threshold
(:data:`~.leaveout.MISFIT_KAPPA`), from the unmasked preparation's fit of runs a and b, and
the runs are prepared again with the mask there. Plain functions.
"""

from __future__ import annotations

import numpy as np

from drivegain.config.robot import Robot
from drivegain.identify.leaveout import MISFIT_KAPPA
from drivegain.identify.reversals import masked_drives

#: ``--reversal-mask``'s value that asks for the gate.
MASK_AUTO = "auto"

#: Taper of the mask the gate applies, s. Over 24 seeds of the study's closed-loop scenarios
#: (benchmarks/study_reversal_mask.py): on random excitations 0.1 s takes 27-56 % off every
#: gain's RMS error against 22-44 % at 0.05 s; on the optimised one ±2σ covers 96.5 % at 0.1 s
#: (99.3 % at 0.05 s, 100 % unmasked), though its j5 and j6 then lean (mean z −0.62, −0.54).
AUTO_TAPER_S = 0.1


def stuck_drives(kappa: np.ndarray, threshold: float = MISFIT_KAPPA) -> tuple[int, ...]:
    """The drives (from 0) whose κ̂ reaches ``threshold``: those that stick at reversals.

    Parameters
    ----------
    kappa
        κ̂ per drive of the unmasked fit of runs a and b, ≥ 0, (n,).
    threshold
        The gate, relative to the drive's own noise variance.

    Raises
    ------
    ValueError
        ``kappa`` not a finite vector.
    """
    k = np.asarray(kappa, dtype=float)
    if k.ndim != 1 or not np.all(np.isfinite(k)):
        raise ValueError(f"kappa must be a finite vector, got {k!r}")
    return tuple(int(i) for i in np.flatnonzero(k >= threshold))


def gate_note(robot: Robot, kappa: np.ndarray, drives: tuple[int, ...]) -> str:
    """The runs' note of the gate's choice: which drives it masked and why."""
    k = np.asarray(kappa, dtype=float)
    shown = ", ".join(f"{name} {v:.2g}" for name, v in zip(robot.joint_names, k, strict=True))
    if not drives:
        return (
            f"reversal mask (auto): no drive sticks at its reversals (κ̂ below {MISFIT_KAPPA:g}: "
            f"{shown}); every equation counts"
        )
    masked = [robot.joint_names[i] for i in np.flatnonzero(masked_drives(robot, drives))]
    return (
        f"reversal mask (auto): {', '.join(masked)} weighted out near their reversals, taper "
        f"{AUTO_TAPER_S:g} s (κ̂ {shown}; {MISFIT_KAPPA:g} or more sticks)"
    )
