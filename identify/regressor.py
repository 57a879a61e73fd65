"""The inverse dynamic identification model (IDIM) regressor, for many samples at once.

``tau = W(q, qd, qdd) @ chi`` with ``chi`` the standard parameters of :mod:`.params`. The rigid
body part is a Newton-Euler recursion vectorised over samples (numpy, world frame); rotor
inertia, friction, offsets and the coupled-motor terms are added as explicit columns.
"""

from __future__ import annotations

import numpy as np

from drivegain.config.robot import WristFriction
from drivegain.identify.model import RobotModel
from drivegain.identify.params import N_INERTIAL, N_PER_JOINT, n_standard


def _as_samples(x: np.ndarray, n: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != n:
        raise ValueError(f"{name} must have shape (samples, {n}), got {np.shape(x)}")
    return a


def _axis_rotation(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) about a fixed unit ``axis`` by ``angle`` (N,) rad."""
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    kk = k @ k
    return np.eye(3)[None] + s[:, None, None] * k[None] + (1.0 - c)[:, None, None] * kk[None]


def _inertia_map(w: np.ndarray) -> np.ndarray:
    """Matrices (N, 3, 6) with ``I @ w = L(w) @ [XX XY XZ YY YZ ZZ]``."""
    nrow = w.shape[0]
    out = np.zeros((nrow, 3, 6))
    wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = wx, wy, wz
    out[:, 1, 1], out[:, 1, 3], out[:, 1, 4] = wx, wy, wz
    out[:, 2, 2], out[:, 2, 4], out[:, 2, 5] = wx, wy, wz
    return out


def _skew_batch(v: np.ndarray) -> np.ndarray:
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def rigid_body_regressor(
    model: RobotModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
) -> np.ndarray:
    """Rigid-body joint torque regressor.

    Parameters
    ----------
    model
        The robot model.
    q, qd, qdd
        Joint positions (rad), velocities (rad/s), accelerations (rad/s²), shape (N, n).

    Returns
    -------
    numpy.ndarray
        Shape (N, n, 10·n): torque of joint i (N·m) per inertial parameter
        ``[XX XY XZ YY YZ ZZ MX MY MZ M]`` of each link j, at the origin of frame j.
    """
    n = model.n
    q, qd, qdd = (_as_samples(x, n, nm) for x, nm in ((q, "q"), (qd, "qd"), (qdd, "qdd")))
    ns = q.shape[0]
    rot = np.broadcast_to(np.eye(3), (ns, 3, 3))
    pos = np.zeros((ns, 3))
    w = np.zeros((ns, 3))
    wd = np.zeros((ns, 3))
    acc = np.broadcast_to(-model.gravity, (ns, 3)).copy()  # gravity as a base acceleration
    origins, axes_w, forces, moments = [], [], [], []
    for j in range(n):
        rot_parent = rot
        r = rot_parent @ model.translations[j]
        rot_fixed = rot_parent @ model.rotations[j]
        z = rot_fixed @ model.axes[j]
        rot = rot_fixed @ _axis_rotation(model.axes[j], q[:, j])
        # Acceleration of the new origin uses the parent's angular motion.
        acc = acc + np.cross(wd, r) + np.cross(w, np.cross(w, r))
        pos = pos + r
        wz = z * qd[:, j, None]
        wd = wd + z * qdd[:, j, None] + np.cross(w, wz)
        w = w + wz
        # Link quantities in the link frame, where its parameters are expressed.
        rt = np.swapaxes(rot, 1, 2)
        wl = np.einsum("nij,nj->ni", rt, w)
        wdl = np.einsum("nij,nj->ni", rt, wd)
        al = np.einsum("nij,nj->ni", rt, acc)
        f_loc = np.zeros((ns, 3, N_INERTIAL))
        n_loc = np.zeros((ns, 3, N_INERTIAL))
        sw, swd, sa = _skew_batch(wl), _skew_batch(wdl), _skew_batch(al)
        # Inertia: n = I wd + w x (I w)
        n_loc[:, :, 0:6] = _inertia_map(wdl) + sw @ _inertia_map(wl)
        # First moment c: f = wd x c + w x (w x c); n = c x a = -a x c
        f_loc[:, :, 6:9] = swd + sw @ sw
        n_loc[:, :, 6:9] = -sa
        # Mass: f = a
        f_loc[:, :, 9] = al
        forces.append(rot @ f_loc)
        moments.append(rot @ n_loc)
        origins.append(pos)
        axes_w.append(z)
    out = np.zeros((ns, n, N_INERTIAL * n))
    for i in range(n):
        for j in range(i, n):
            d = origins[j] - origins[i]
            # Moment about origin i of the wrench of link j, projected on axis i.
            m_i = moments[j] + np.cross(d[:, :, None], forces[j], axis=1)
            out[:, i, N_INERTIAL * j : N_INERTIAL * (j + 1)] = np.einsum(
                "nk,nkp->np", axes_w[i], m_i
            )
    return out


def standard_regressor(
    model: RobotModel,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    wrist_friction: WristFriction | str | None = None,
) -> np.ndarray:
    """IDIM regressor on the standard parameters (see :mod:`drivegain.identify.params`).

    Parameters
    ----------
    model
        The robot model.
    q, qd, qdd
        Joint positions (rad, controller convention), velocities (rad/s), accelerations (rad/s²),
        shape (N, n).
    wrist_friction
        Friction form of coupled motors; default: the robot file's choice.

    Returns
    -------
    numpy.ndarray
        Shape (N, n, n_standard): joint torques (N·m) per standard parameter.
    """
    robot = model.robot
    n = robot.n
    form = WristFriction(wrist_friction or robot.wrist_friction)
    q, qd, qdd = (_as_samples(x, n, nm) for x, nm in ((q, "q"), (qd, "qd"), (qdd, "qdd")))
    ns = q.shape[0]
    out = np.zeros((ns, n, n_standard(robot)))
    rb = rigid_body_regressor(model, q, qd, qdd)
    for j in range(n):
        base = N_PER_JOINT * j
        out[:, :, base : base + N_INERTIAL] = rb[:, :, N_INERTIAL * j : N_INERTIAL * (j + 1)]
        out[:, j, base + 10] = qdd[:, j]
        out[:, j, base + 11] = qd[:, j]
        out[:, j, base + 12] = np.sign(qd[:, j])
        out[:, j, base + 13] = 1.0
    for k, c in enumerate(robot.couplings):
        m, o = c.motor, c.joint
        ia = N_PER_JOINT * m + 10
        # Motor m turns with q_m + q_o: its rotor inertia couples the two rows.
        out[:, o, ia] = qdd[:, m]
        out[:, m, ia] += qdd[:, o]
        col = N_PER_JOINT * n + 2 * k
        out[:, o, col] = qd[:, m]
        out[:, m, col] = qd[:, o]
        s_sum = np.sign(qd[:, o] + qd[:, m])
        if form is WristFriction.PHYSICAL:
            out[:, o, col + 1] = s_sum
            out[:, m, col + 1] = s_sum
        else:  # the paper's eq. (22) as printed
            s_m = np.sign(qd[:, m])
            out[:, o, col + 1] = s_m
            out[:, m, col + 1] = s_sum - s_m
    return out


def payload_columns(model: RobotModel, link: int) -> slice:
    """Standard-regressor columns whose torques a payload on ``link`` (1-based) produces."""
    base = N_PER_JOINT * (link - 1)
    return slice(base, base + N_INERTIAL)


def stack_joint_major(x: np.ndarray) -> np.ndarray:
    """Stack per-sample rows joint by joint: (N, n) -> (n·N,) or (N, n, p) -> (n·N, p)."""
    a = np.asarray(x)
    if a.ndim == 2:
        return a.T.reshape(-1)
    if a.ndim == 3:
        return a.transpose(1, 0, 2).reshape(-1, a.shape[2])
    raise ValueError(f"expected a 2-D or 3-D array, got shape {a.shape}")
