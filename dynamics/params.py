"""The standard dynamic parameters: layout, names, and vectors built from known values.

Layout (the paper's, eq. 2): for each joint j, 14 parameters
``XXj XYj XZj YYj YZj ZZj MXj MYj MZj Mj Iaj Fvj Fcj OFFj`` (inertia at the origin of frame j,
tensor elements; first moments; mass; rotor inertia; viscous and Coulomb friction; torque
offset), then for each coupled motor m two parameters ``fvmM fcmM``. The TX-40 has 14·6 + 2 = 86.
"""

from __future__ import annotations

import numpy as np

from drivegain.config.payload import PAYLOAD_PARAMS, Payload
from drivegain.config.robot import Robot
from drivegain.config.truth import Truth

#: Names of the 14 per-joint parameters, in layout order.
PER_JOINT = (*PAYLOAD_PARAMS, "Ia", "Fv", "Fc", "OFF")
N_PER_JOINT = len(PER_JOINT)
N_INERTIAL = 10


def n_standard(robot: Robot) -> int:
    """Number of standard parameters: 14 per joint plus 2 per coupled motor."""
    return N_PER_JOINT * robot.n + 2 * len(robot.couplings)


def standard_names(robot: Robot) -> list[str]:
    """Readable names of the standard parameters, e.g. ``ZZ1``, ``Ia6``, ``fvm6``."""
    names = [f"{p}{j + 1}" for j in range(robot.n) for p in PER_JOINT]
    for c in robot.couplings:
        names += [f"fvm{c.motor + 1}", f"fcm{c.motor + 1}"]
    return names


def inertial_slice(j: int) -> slice:
    """Columns of the 10 inertial parameters of link ``j`` (0-based)."""
    return slice(N_PER_JOINT * j, N_PER_JOINT * j + N_INERTIAL)


def index(robot: Robot, name: str) -> int:
    """Column index of a standard parameter by name."""
    return standard_names(robot).index(name)


def inertial_vector(mass: float, first_moment: np.ndarray, inertia: np.ndarray) -> np.ndarray:
    """The 10 inertial parameters ``[XX XY XZ YY YZ ZZ MX MY MZ M]`` of one body."""
    return np.concatenate([np.asarray(inertia, float), np.asarray(first_moment, float), [mass]])


def truth_vector(robot: Robot, truth: Truth) -> np.ndarray:
    """Standard parameter vector of a simulation truth (without payload)."""
    chi = np.zeros(n_standard(robot))
    for j, link in enumerate(truth.links):
        base = N_PER_JOINT * j
        chi[base : base + N_INERTIAL] = inertial_vector(link.mass, link.first_moment, link.inertia)
        chi[base + 10 : base + 14] = [link.Ia, link.Fv, link.Fc, link.offset]
    for k, _c in enumerate(robot.couplings):
        off = N_PER_JOINT * robot.n + 2 * k
        chi[off : off + 2] = [truth.fvm, truth.fcm]
    return chi


def with_payload(robot: Robot, chi: np.ndarray, payload: Payload) -> np.ndarray:
    """``chi`` with the payload's inertial parameters added to the link it is fixed to.

    The payload frame is the link frame (sigma = 2 with a zero transform), so its parameters add
    to the link's. Parameters without a value in the payload file count as zero.
    """
    out = np.array(chi, dtype=float, copy=True)
    out[inertial_slice(payload.link - 1)] += np.nan_to_num(payload.values, nan=0.0)
    return out


def to_pinocchio_order(inertial10: np.ndarray) -> np.ndarray:
    """Our inertial order -> Pinocchio's ``[m mx my mz Ixx Ixy Iyy Ixz Iyz Izz]``."""
    xx, xy, xz, yy, yz, zz, mx, my, mz, m = inertial10
    return np.array([m, mx, my, mz, xx, xy, yy, xz, yz, zz])


#: Our inertial order expressed as indices into Pinocchio's order.
FROM_PINOCCHIO = np.array([4, 5, 7, 6, 8, 9, 1, 2, 3, 0])
