"""Where a drive's current carries Coulomb friction the model cannot follow: velocity reversals.

The IDIM models Coulomb friction as ``Fc · sign(v)`` of a velocity v (a joint's, or a coupled
motor's). Near a reversal of v a drive train driven in closed loop sticks: the friction holds
whatever torque the controller applies, anywhere between −Fc and +Fc, until the loop has built
up the torque that breaks it loose. Those stretches (tens of ms per reversal, longer when the
reversal is slow) carry an equation error of up to 2·Fc in the currents the friction term
enters. The error has the sign of the reversal, so it is correlated with the Coulomb columns
and biases the gains: on the simulated cell's closed-loop drives with random excitations, by
0.5-10 % RMS per joint (docs/model.md, "Reversals").

:func:`reversal_marks` marks, per sample and drive, whether a Coulomb velocity entering that
drive's current is near zero. The preparation decimates the mark with the regressor's filter,
so each decimated entry knows the share of its filter window near a reversal
(:attr:`~drivegain.identify.prepare.PreparedRun.reversal_share`). In the maximum-likelihood
gains an entry with share s has (1 + κ s) times the variance of one away from reversals, κ
estimated per drive from the residuals (:class:`~drivegain.identify.mlmodel.Whitening`): where
the data show no excess κ is about 0 and every entry counts alike, where they do the entries
near reversals count less.

Down-weighting leaves a bias: the misfit is not noise but has the sign of the velocity. While a
velocity crawls through zero the friction ramps from one side to the other instead of jumping,
so inside the zone its mean is smaller than ``Fc`` and of the same sign as the (filtered)
velocity. :func:`reversal_marks` also gives that velocity's sign inside the zone only; as a
regressor column of its own (a Coulomb coefficient that holds near reversals,
:func:`reversal_entries`) it takes up the mean of the misfit, which would otherwise go to the
gains (:attr:`~drivegain.identify.prepare.PreparedRun.reversal_coulomb`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.sparse.csgraph import connected_components

from drivegain.config.robot import Robot

#: A Coulomb velocity below this fraction of its RMS over the run counts as reversing (joints
#: of an excitation reverse at 0.5-1.5 rad/s² with RMS speeds of 0.3-1 rad/s: 40-400 ms per
#: reversal). Of 0.05, 0.1, 0.2 and 0.3, tried on the closed-loop drives with random
#: excitations (3 seeds, with a first variance model of three levels of share), 0.1 left the
#: smallest gain errors.
REVERSAL_FRACTION = 0.1
#: A velocity gets a reversal Coulomb column only when its zone holds this share of the run's
#: samples at least (fewer: the column is too short-lived to be told from the noise) ...
MIN_ZONE_SHARE = 0.005
#: ... and at most this share (more: the column is most of its Coulomb column, which it would
#: then duplicate; a joint that barely moves).
MAX_ZONE_SHARE = 0.5


def coulomb_sources(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """The velocities whose sign enters Coulomb friction, and the drives each enters.

    Returns
    -------
    velocity : numpy.ndarray
        (r, n): row s gives velocity s = ``velocity[s] @ q̇`` (the joints' own velocities, then
        each coupled motor's, joint side).
    drives : numpy.ndarray
        (r, n) bool: drive i's current carries the friction of velocity s. The current matrix
        of eq. (21) mixes the joint torques into the currents: a joint's friction reaches every
        drive that carries its torque, and a coupled motor's (which acts on all the joints it
        couples) only that motor's own current.
    """
    k = robot.transmission()
    scale = np.diag(k)
    # eq. (21)'s coupling factor, as design.coupling_factor (which imports this module's
    # importer, prepare): torques -> drive currents, up to the gains.
    to_current = np.linalg.inv(k.T / scale[None, :])
    coupled = [k[m] / scale[m] for m in range(robot.n) if np.count_nonzero(k[m]) > 1]
    # A joint's friction is a torque on its own joint along its own velocity; a coupled motor's
    # acts on the joints it couples in the proportions of its velocity (virtual work): the same
    # row serves as the velocity and as the friction's joint torques.
    velocity = np.vstack([np.eye(robot.n), *coupled])
    reach = np.abs(velocity @ to_current.T) > 1e-9 * np.abs(to_current).max()
    return velocity, reach


def reversal_marks(
    qd: np.ndarray, robot: Robot, fraction: float = REVERSAL_FRACTION
) -> tuple[np.ndarray, np.ndarray]:
    """Where each drive is near a reversal, and each Coulomb velocity's sign there.

    Parameters
    ----------
    qd
        Filtered joint velocities, rad/s, (N, n).
    robot
        The robot (its couplings decide which velocities have Coulomb friction:
        :func:`coulomb_sources`).
    fraction
        A velocity below this fraction of its RMS over the run counts as reversing.

    Returns
    -------
    zones : numpy.ndarray
        (N, n) float, 1 or 0: the samples where a Coulomb velocity whose friction reaches drive
        i's current is near a reversal.
    signs : numpy.ndarray
        (N, r), -1, 0 or 1: each Coulomb velocity's sign where it is near a reversal, 0
        elsewhere. A velocity whose zone holds less than :data:`MIN_ZONE_SHARE` or more than
        :data:`MAX_ZONE_SHARE` of the samples gets zeros (no column).
    """
    velocity, reach = coulomb_sources(robot)
    v = np.asarray(qd, dtype=float) @ velocity.T  # (N, r)
    rms = np.sqrt(np.mean(v**2, axis=0))
    near = np.abs(v) <= fraction * np.where(rms > 0.0, rms, np.inf)
    zones = np.asarray((near.astype(float) @ reach.astype(float)) > 0.0, dtype=float)
    share = near.mean(axis=0) if near.shape[0] else np.zeros(near.shape[1])
    usable = (share >= MIN_ZONE_SHARE) & (share <= MAX_ZONE_SHARE)
    return zones, np.asarray(np.where(near & usable[None, :], np.sign(v), 0.0))


def reversal_entries(robot: Robot) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the reversal Coulomb column of each velocity enters the joint torques.

    A velocity's friction acts on the joints it moves, in the proportions of its velocity
    (virtual work, as in :func:`coulomb_sources`).

    Returns
    -------
    joint, source, weight
        (m,) each: joint torque ``joint`` gets ``weight`` times the signs of velocity
        ``source`` (:func:`reversal_marks`) per unit of its coefficient (N·m).
    """
    velocity = coulomb_sources(robot)[0]
    source, joint = np.nonzero(velocity)
    return joint.astype(np.intp), source.astype(np.intp), velocity[source, joint]


def source_names(robot: Robot) -> list[str]:
    """Names of the velocities of :func:`coulomb_sources`: each joint's, then each coupled
    motor's (``motor j5+j6``)."""
    velocity = coulomb_sources(robot)[0]
    names = list(robot.joint_names)
    for row in velocity[robot.n :]:
        names.append("motor " + "+".join(robot.joint_names[j] for j in np.flatnonzero(row)))
    return names


def masked_drives(robot: Robot, drives: Sequence[int] | None) -> np.ndarray:
    """(n,) bool: the drives :func:`reversal_mask` weights given ``drives``, each with its
    coupled group (None: all).

    Raises
    ------
    ValueError
        A drive out of range.
    """
    if drives is None:
        return np.ones(robot.n, dtype=bool)
    idx = np.asarray(drives, dtype=int).reshape(-1)
    if np.any((idx < 0) | (idx >= robot.n)):
        raise ValueError(f"drives are 0 to {robot.n - 1}, got {list(map(int, idx))}")
    group = coupled_blocks(robot)
    return np.isin(group, group[idx])


def coupled_blocks(robot: Robot) -> np.ndarray:
    """Which drives a coupling ties together: the connected groups of the transmission matrix.

    Returns
    -------
    numpy.ndarray
        (n,) int: drive i's group label, numbered from 0 in the order of the drives (the TX-40:
        0 1 2 3 4 4).
    """
    k = robot.transmission()
    return np.asarray(connected_components((k != 0.0) | (k.T != 0.0), directed=False)[1])


def reversal_mask(
    zones: np.ndarray,
    robot: Robot,
    rate_hz: float,
    taper_s: float,
    drives: Sequence[int] | None = None,
) -> np.ndarray:
    """Weights that take the equations near reversals out of a fit, at the full rate.

    A drive that sticks at a reversal leaves an equation error no column of the model follows
    (the friction holds any torque in [−Fc, Fc]), and after it a catch-up whose fast torque the
    filtered positions do not carry. Multiplying both sides of every equation by the same weight
    before the decimation keeps ``Y = W χ`` exact and leaves those stretches out. The weight is
    0 inside every reversal zone of the drives of a coupled group (:func:`coupled_blocks`: the
    current matrix mixes their torques, so their equations are weighted alike) and rises as a
    raised cosine to 1 over ``taper_s`` either side: a step would bring the currents' fast
    content the decimation filter removes down into its pass band.

    Parameters
    ----------
    zones
        (N, n) of :func:`reversal_marks`, 1 near a reversal reaching drive i.
    robot
        The robot (its couplings).
    rate_hz
        Sample rate, Hz.
    taper_s
        Width of the rise either side of a zone, s (> 0).
    drives
        The drives (from 0) whose coupled groups are weighted; the other groups keep weight 1.
        None: every group.

    Returns
    -------
    numpy.ndarray
        (N, n) in [0, 1]: the weight of drive i's current and of joint i's equations.

    Raises
    ------
    ValueError
        ``taper_s`` or ``rate_hz`` not positive, ``zones`` not (N, n), or a drive out of range.
    """
    zones = np.asarray(zones, dtype=float)
    if not (np.isfinite(taper_s) and taper_s > 0.0):
        raise ValueError(f"taper_s must be positive, got {taper_s}")
    if not (np.isfinite(rate_hz) and rate_hz > 0.0):
        raise ValueError(f"rate_hz must be positive, got {rate_hz}")
    if zones.ndim != 2 or zones.shape[1] != robot.n:
        raise ValueError(f"zones must be (N, {robot.n}), got {zones.shape}")
    width = taper_s * rate_hz  # samples
    group = coupled_blocks(robot)
    chosen = np.unique(group[masked_drives(robot, drives)])
    t = np.arange(zones.shape[0])
    out = np.ones_like(zones)
    for g in chosen:
        marked = np.flatnonzero((zones[:, group == g] > 0.0).any(axis=1))
        if marked.size == 0:
            continue
        # samples to the nearest marked sample, on either side
        right = np.searchsorted(marked, t).clip(max=marked.size - 1)
        left = (right - 1).clip(min=0)
        dist = np.minimum(np.abs(t - marked[right]), np.abs(t - marked[left])).astype(float)
        weight = np.where(dist >= width, 1.0, 0.5 - 0.5 * np.cos(np.pi * dist / width))
        out[:, group == g] = weight[:, None]
    return out
