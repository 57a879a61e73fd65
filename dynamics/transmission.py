"""Transmission between motors and joints, and the coupled current matrix of eq. (21).

Motor angles are ``q_m = K @ q`` with ``K = diag(N)`` plus one entry per coupled motor (for the
TX-40, motor 6 turns with N6·(q5 + q6)). By power conservation joint torques are
``tau = K.T @ tau_m``.
"""

from __future__ import annotations

import numpy as np

from drivegain.config.robot import Robot


def joint_to_motor(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Motor angles (rad) from joint angles (rad); ``q`` has shape (..., n)."""
    return np.asarray(q, dtype=float) @ robot.transmission().T


def motor_to_joint(robot: Robot, q_motor: np.ndarray) -> np.ndarray:
    """Joint angles (rad) from motor angles (rad); ``q_motor`` has shape (..., n)."""
    k = robot.transmission()
    return np.linalg.solve(k, np.asarray(q_motor, dtype=float).T).T


def motor_to_joint_torque(robot: Robot, tau_motor: np.ndarray) -> np.ndarray:
    """Joint torques (N·m) from motor torques (N·m): ``tau = K.T @ tau_m``."""
    return np.asarray(tau_motor, dtype=float) @ robot.transmission()


def current_matrix(robot: Robot, current: np.ndarray) -> np.ndarray:
    """The matrix V of eq. (21) with ``tau = V @ g`` for drive gains g (N·m/A, joint side).

    Gain g_j = N_j·(motor torque per ampere of drive j), so with motor torques (g_j/N_j)·v_j the
    joint torques are K.T @ tau_m: a coupled motor m contributes g_m·v_m to the row of the joint
    it is coupled to as well as to its own.

    Parameters
    ----------
    robot
        The robot (for its transmission).
    current
        Current references v (A), shape (N, n).

    Returns
    -------
    numpy.ndarray
        Shape (N, n, n).
    """
    v = np.asarray(current, dtype=float)
    k = robot.transmission()
    # kt[i, j] = K[j, i] / N_j: 1 on the diagonal, 1 where motor j also drives joint i.
    kt = k.T / np.diag(k)[None, :]
    return kt[None, :, :] * v[:, None, :]


def joint_torque(robot: Robot, current: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """Joint torques (N·m) produced by current references (A) through gains (N·m/A)."""
    return np.einsum("nij,j->ni", current_matrix(robot, current), np.asarray(gains, float))


def currents_for_torque(robot: Robot, tau: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """Current references (A) that produce joint torques ``tau`` (N·m): the inverse of
    :func:`joint_torque`."""
    k = robot.transmission()
    kt = k.T / np.diag(k)[None, :]
    a = kt * np.asarray(gains, float)[None, :]
    return np.linalg.solve(a, np.asarray(tau, dtype=float).T).T
