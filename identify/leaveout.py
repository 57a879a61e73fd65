"""Which entries of Case 2's equations to leave out: those near reversals of misfit drives.

A drive in closed loop sticks at a velocity reversal, so the entries of the joints it carries
there hold an equation error of up to 2·Fc that no column of the model follows
(:mod:`drivegain.identify.reversals`). The maximum-likelihood gains measure, per drive, how much
variance those entries add (κ̂); where it is large, Case 2 after those gains leaves the entries
out of every product of its rows (``Design.row_weight``) rather than letting them pull the
payload's parameters (docs/model.md, "Case 2 without the misfit reversals").
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from drivegain.identify.casenoise import CaseNoise
from drivegain.identify.design import Design

#: An entry of a drive counts as near a reversal when more than this share of its decimation
#: filter's window is (``PreparedRun.reversal_share``) ...
REVERSAL_SHARE_LIMIT = 0.05
#: ... and so do this many decimated samples either side of it (the drive sticks longer than
#: its velocity stays below the mark: 0, 2 and 5 tried on random excitations in closed loop,
#: docs/model.md).
REVERSAL_MARGIN = 2


#: A drive's entries near its reversals are misfit when the maximum-likelihood gains' κ̂ (the
#: variance they add per unit share of reversal, relative to the drive's noise) is at least
#: this: the drive sticks there (closed loop: κ̂ 1.7-10 per drive on the simulated cell) or its
#: Coulomb sign is uncertain (a slow reversal under the encoder's quantum); where neither, κ̂
#: stayed below 0.7 (docs/model.md, "Case 2 without the misfit reversals").
MISFIT_KAPPA = 1.0


def misfit_drives(noise: CaseNoise) -> np.ndarray:
    """Which drives' entries near reversals the gains' error model finds misfit:
    κ̂ ≥ :data:`MISFIT_KAPPA`.

    Returns
    -------
    numpy.ndarray
        (n,) bool, per drive.
    """
    return np.asarray(noise.whitening.kappa, dtype=float) >= MISFIT_KAPPA


def near_reversals(
    d: Design,
    limit: float = REVERSAL_SHARE_LIMIT,
    margin: int = REVERSAL_MARGIN,
    drives: np.ndarray | None = None,
) -> np.ndarray:
    """Which entries of each joint's equations lie near a reversal of a drive they carry.

    Joint j's torque is carried by the drives its row of the coupled current matrix reaches
    (``kt[j] != 0``); its entry k is near a reversal when one of those drives (of ``drives``)
    has more than ``limit`` of its filter window near one at a sample within ``margin`` of k.

    Parameters
    ----------
    d
        The design.
    limit
        Share of the window (0-1).
    margin
        Samples either side (≥ 0).
    drives
        (n,) bool: the drives whose reversals count (None: all).

    Returns
    -------
    numpy.ndarray
        (N, n) bool, all False when the run has no reversal shares.

    Raises
    ------
    ValueError
        ``limit`` outside [0, 1) or a negative ``margin``.
    """
    if not 0.0 <= limit < 1.0:
        raise ValueError(f"limit must be in [0, 1), got {limit}")
    if margin < 0:
        raise ValueError(f"margin must be 0 or more, got {margin}")
    n = d.n
    out = np.zeros((d.rows, n), dtype=bool)
    share = d.run.reversal_share
    if share is None:
        return out
    marked = np.abs(share) > limit  # (N, drives)
    if drives is not None:
        drives = np.asarray(drives, dtype=bool)
        if drives.shape != (marked.shape[1],):
            raise ValueError(f"drives must be ({marked.shape[1]},) bool, got {drives.shape}")
        marked &= drives[None, :]
    window = np.ones(2 * margin + 1)
    for j in range(n):
        rows = marked[:, d.kt[j] != 0.0].any(axis=1)
        out[:, j] = np.convolve(rows.astype(float), window, mode="same") > 0.0
    return out


def without_rows(d: Design, drop: np.ndarray) -> Design:
    """``d`` with the entries ``drop`` ((N, n) bool) left out of every fit of its rows."""
    drop = np.asarray(drop, dtype=bool)
    if drop.shape != (d.rows, d.n):
        raise ValueError(f"drop must be ({d.rows}, {d.n}), got {drop.shape}")
    weight = (~drop).astype(float)
    if d.row_weight is not None:
        weight *= d.row_weight
    return replace(d, row_weight=weight)
