"""Rigid-body model of a serial robot: Pinocchio model built from an MDH table or a URDF."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from drivegain.config.robot import Robot
from drivegain.errors import ModelError

_AXES = {
    "JointModelRX": np.array([1.0, 0.0, 0.0]),
    "JointModelRY": np.array([0.0, 1.0, 0.0]),
    "JointModelRZ": np.array([0.0, 0.0, 1.0]),
}


@dataclass(frozen=True)
class RobotModel:
    """A robot description with its kinematic chain.

    Attributes
    ----------
    robot
        The validated description.
    pin_model
        The Pinocchio model (one revolute joint per robot joint, bodies without inertia).
    rotations, translations
        Placement of each joint frame in its parent frame at q = 0: (n, 3, 3) and (n, 3), m.
    axes
        Unit rotation axis of each joint in its own frame, (n, 3).
    gravity
        Gravity vector in the base frame, m/s².
    """

    robot: Robot
    pin_model: pin.Model
    rotations: np.ndarray
    translations: np.ndarray
    axes: np.ndarray
    gravity: np.ndarray

    @property
    def n(self) -> int:
        return self.robot.n


def mdh_placement(alpha: float, d: float, theta_offset: float, r: float) -> pin.SE3:
    """Frame j in frame j-1 for q_j = 0: Rx(alpha)·Tx(d)·Rz(theta_offset)·Tz(r) (Khalil MDH)."""
    rx = pin.SE3(pin.utils.rotate("x", alpha), np.zeros(3))
    tx = pin.SE3(np.eye(3), np.array([d, 0.0, 0.0]))
    rz = pin.SE3(pin.utils.rotate("z", theta_offset), np.zeros(3))
    tz = pin.SE3(np.eye(3), np.array([0.0, 0.0, r]))
    return rx * tx * rz * tz


def _model_from_mdh(robot: Robot) -> pin.Model:
    model = pin.Model()
    model.name = robot.name
    parent = 0
    for joint in robot.joints:
        assert joint.mdh is not None  # guaranteed by the loader when no URDF is given
        if joint.mdh.sigma != 0:
            raise ModelError(f"joint {joint.name}: only revolute joints are supported")
        placement = mdh_placement(joint.mdh.alpha, joint.mdh.d, joint.mdh.theta_offset, joint.mdh.r)
        jid = model.addJoint(parent, pin.JointModelRZ(), placement, joint.name)
        # Zero inertia: the dynamic parameters come from the identification vector.
        model.appendBodyToJoint(jid, pin.Inertia.Zero(), pin.SE3.Identity())
        parent = jid
    return model


def build_model(robot: Robot) -> RobotModel:
    """Build the kinematic chain of ``robot`` (from its URDF if it names one, else its MDH rows).

    Raises
    ------
    ModelError
        The chain is not serial, a joint is not revolute, or the joint count differs from the
        robot description.
    """
    if robot.urdf is not None:
        try:
            model = pin.buildModelFromUrdf(str(robot.urdf))
        except (RuntimeError, ValueError) as exc:
            raise ModelError(f"{robot.urdf}: cannot build a model ({exc})") from None
    else:
        model = _model_from_mdh(robot)
    n = model.njoints - 1
    if n != robot.n or model.nq != robot.n:
        raise ModelError(f"the model has {model.nq} coordinates, the robot file {robot.n} joints")
    rotations = np.empty((n, 3, 3))
    translations = np.empty((n, 3))
    axes = np.empty((n, 3))
    for i in range(1, n + 1):
        if model.parents[i] != i - 1:
            raise ModelError(f"joint {model.names[i]}: only serial chains are supported")
        jm = model.joints[i]
        short = jm.shortname()
        if short in _AXES:
            axis = _AXES[short]
        elif short == "JointModelRevoluteUnaligned":
            axis = np.asarray(jm.extract().axis, dtype=float)
        else:
            raise ModelError(f"joint {model.names[i]}: unsupported joint type {short}")
        rotations[i - 1] = model.jointPlacements[i].rotation
        translations[i - 1] = model.jointPlacements[i].translation
        axes[i - 1] = axis / np.linalg.norm(axis)
    model.gravity.linear = np.asarray(robot.gravity, dtype=float)
    return RobotModel(
        robot=robot,
        pin_model=model,
        rotations=rotations,
        translations=translations,
        axes=axes,
        gravity=np.asarray(robot.gravity, dtype=float).copy(),
    )
