"""Where a drive's current carries Coulomb friction the model cannot follow: velocity reversals.

The IDIM models Coulomb friction as ``Fc · sign(v)`` of a velocity v (a joint's, or a coupled
motor's). Near a reversal of v a drive train driven in closed loop sticks: the friction holds
whatever torque the controller applies, anywhere between −Fc and +Fc, until the loop has built
up the torque that breaks it loose. Those stretches (tens of ms per reversal, longer when the
reversal is slow) carry an equation error of up to 2·Fc in the currents the friction term
enters. The error has the sign of the reversal, so it is correlated with the Coulomb columns
and biases the gains: on the simulated cell's closed-loop drives with random excitations, by
0.5-10 % RMS per joint (docs/model.md, "Reversals").

:func:`reversal_zones` marks, per sample and drive, whether a Coulomb velocity entering that
drive's current is near zero. The preparation decimates the mark with the regressor's filter,
so each decimated entry knows the share of its filter window near a reversal
(:attr:`~drivegain.identify.prepare.PreparedRun.reversal_share`). In the maximum-likelihood
gains an entry with share s has (1 + κ s) times the variance of one away from reversals, κ
estimated per drive from the residuals (:class:`~drivegain.identify.mlmodel.Whitening`): where
the data show no excess κ is about 0 and every entry counts alike, where they do the entries
near reversals count less.
"""

from __future__ import annotations

import numpy as np

from drivegain.config.robot import Robot

#: A Coulomb velocity below this fraction of its RMS over the run counts as reversing (joints
#: of an excitation reverse at 0.5-1.5 rad/s² with RMS speeds of 0.3-1 rad/s: 40-400 ms per
#: reversal). Of 0.05, 0.1, 0.2 and 0.3, tried on the closed-loop drives with random
#: excitations (3 seeds, with a first variance model of three levels of share), 0.1 left the
#: smallest gain errors.
REVERSAL_FRACTION = 0.1


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


def reversal_zones(qd: np.ndarray, robot: Robot, fraction: float = REVERSAL_FRACTION) -> np.ndarray:
    """Samples near a reversal of a Coulomb term of each drive: (N, n) float, 1 or 0.

    Parameters
    ----------
    qd
        Filtered joint velocities, rad/s, (N, n).
    robot
        The robot (its couplings decide which velocities have Coulomb friction).
    fraction
        A velocity below this fraction of its RMS over the run counts as reversing.
    """
    velocity, reach = coulomb_sources(robot)
    v = np.abs(np.asarray(qd, dtype=float) @ velocity.T)  # (N, r)
    rms = np.sqrt(np.mean(v**2, axis=0))
    near = v <= fraction * np.where(rms > 0.0, rms, np.inf)
    return np.asarray((near.astype(float) @ reach.astype(float)) > 0.0, dtype=float)
