"""Power balance of the regressor's inverse dynamics along a smooth trajectory.

Over [0, t]: ∫ τ·q̇ dt = ΔE + ∫ D dt + Σ_j OFF_j Δq_j, with τ = W(q, q̇, q̈) χ from the regressor and,
computed without it, the energy E = kinetic + potential of the links (Pinocchio, inertias set
from χ) + kinetic energy of the rotors, and the friction power D written out from docs/model.md.
For the TX-40 the rotor of motor 6 turns with q5 + q6, so its kinetic energy is
½(Ia5 − Ia6) q̇5² + ½ Ia6 (q̇5 + q̇6)² (Ia5 = K5²Ja5 + K6²Ja6, Ia6 = K6²Ja6).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from scipy.integrate import cumulative_simpson

from drivegain.config import load_robot, load_truth, resource_path
from drivegain.config.robot import Robot, WristFriction
from drivegain.dynamics.model import RobotModel, build_model
from drivegain.dynamics.params import standard_names, truth_vector
from drivegain.dynamics.regressor import standard_regressor

DATA = Path(__file__).resolve().parents[1] / "data"
PIN_ORDER = ("M", "MX", "MY", "MZ", "XX", "XY", "YY", "XZ", "YZ", "ZZ")
DURATION, RATE = 2.0, 2000.0  # s, Hz


def trajectory(n: int, seed: int) -> tuple[np.ndarray, ...]:
    """Sums of sines: time (s) and exact q (rad), q̇ (rad/s), q̈ (rad/s²), each (N, n)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, DURATION, int(DURATION * RATE) + 1)
    omega = 2 * np.pi * np.array([0.45, 0.9, 1.65])  # not periodic over DURATION
    amp = rng.uniform(0.2, 0.6, (n, 3))
    phase = rng.uniform(0, 2 * np.pi, (n, 3))
    arg = t[:, None, None] * omega[None, None, :] + phase[None]
    q = rng.uniform(-1, 1, n) + np.sum(amp * np.sin(arg), axis=2)
    qd = np.sum(amp * omega * np.cos(arg), axis=2)
    qdd = -np.sum(amp * omega**2 * np.sin(arg), axis=2)
    return t, q, qd, qdd


def parameters(model: RobotModel) -> np.ndarray:
    """χ: the TX-40 simulation truth, or arm4's URDF inertias; drive terms and offsets made up."""
    robot = model.robot
    col = {name: k for k, name in enumerate(standard_names(robot))}
    if robot.couplings:
        chi = truth_vector(robot, load_truth(resource_path("sim/tx40-truth.toml")))
    else:
        chi = np.zeros(len(col))
        for j in range(robot.n):
            dyn = model.pin_model.inertias[j + 1].toDynamicParameters()
            for name, value in zip(PIN_ORDER, dyn, strict=True):
                chi[col[f"{name}{j + 1}"]] = value
            chi[col[f"Ia{j + 1}"]] = 0.05 * (j + 1)
            chi[col[f"Fv{j + 1}"]] = 1.5
            chi[col[f"Fc{j + 1}"]] = 2.0
    for j in range(robot.n):
        chi[col[f"OFF{j + 1}"]] = 0.3 * (-1) ** j  # nonzero, so the offset work counts
    return chi


def p(robot: Robot, chi: np.ndarray, name: str) -> float:
    return float(chi[standard_names(robot).index(name)])


def link_energy(model: RobotModel, chi: np.ndarray, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
    """Kinetic + potential energy of the links (J), from Pinocchio with χ's inertias."""
    pm = pin.Model(model.pin_model)
    for j in range(model.n):
        dyn = [p(model.robot, chi, f"{name}{j + 1}") for name in PIN_ORDER]
        pm.inertias[j + 1] = pin.Inertia.FromDynamicParameters(np.array(dyn))
    data = pm.createData()
    return np.array(
        [
            pin.computeKineticEnergy(pm, data, q[k], qd[k])
            + pin.computePotentialEnergy(pm, data, q[k])
            for k in range(len(q))
        ]
    )


def rotor_energy(
    robot: Robot, chi: np.ndarray, qd: np.ndarray, *, coupled: bool = True
) -> np.ndarray:
    """Kinetic energy of the rotors (J); ``coupled=False`` is the naive ½ Σ Ia q̇² (wrong here)."""
    ia = np.array([p(robot, chi, f"Ia{j + 1}") for j in range(robot.n)])
    if not coupled:
        return 0.5 * np.sum(ia * qd**2, axis=1)
    coupled_joints = {j for c in robot.couplings for j in (c.motor, c.joint)}
    energy = 0.5 * sum(ia[j] * qd[:, j] ** 2 for j in range(robot.n) if j not in coupled_joints)
    for c in robot.couplings:
        m, o = c.motor, c.joint  # TX-40: m = joint 6, o = joint 5; rotor 6 turns with q5 + q6
        energy = energy + 0.5 * (ia[o] - ia[m]) * qd[:, o] ** 2
        energy = energy + 0.5 * ia[m] * (qd[:, o] + qd[:, m]) ** 2
    return np.asarray(energy)


def friction_power(
    robot: Robot, chi: np.ndarray, qd: np.ndarray, form: WristFriction
) -> np.ndarray:
    """Power (W) of the friction torques, as model.md defines them for each friction form."""
    power = np.zeros(len(qd))
    for j in range(robot.n):
        v = qd[:, j]
        power += p(robot, chi, f"Fv{j + 1}") * v**2 + p(robot, chi, f"Fc{j + 1}") * np.abs(v)
    for c in robot.couplings:
        m, o = c.motor, c.joint
        fvm, fcm = p(robot, chi, f"fvm{m + 1}"), p(robot, chi, f"fcm{m + 1}")
        v_motor = qd[:, o] + qd[:, m]
        # Viscous: row o gets fvm q̇_m, row m gets fvm q̇_o (the diagonal parts sit in Fv).
        power += fvm * (qd[:, m] * qd[:, o] + qd[:, o] * qd[:, m])
        if form is WristFriction.PHYSICAL:
            power += fcm * np.abs(v_motor)
        else:
            power += fcm * (np.sign(qd[:, m]) * qd[:, o])
            power += fcm * (np.sign(v_motor) - np.sign(qd[:, m])) * qd[:, m]
    return power


CASES = [("tx40.toml", WristFriction.PHYSICAL), ("tx40.toml", WristFriction.PAPER), ("arm4", None)]


@pytest.mark.parametrize(("robot_file", "form"), CASES)
def test_power_balance(robot_file: str, form: WristFriction | None) -> None:
    path = DATA / "arm4.toml" if robot_file == "arm4" else resource_path(robot_file)
    model = build_model(load_robot(path))
    robot = model.robot
    form = form or robot.wrist_friction
    chi = parameters(model)
    t, q, qd, qdd = trajectory(robot.n, seed=1)
    if robot.couplings:
        c = robot.couplings[0]
        v = qd[:, c.joint] + qd[:, c.motor]
        assert np.any(v[1:] * v[:-1] < 0), "the coupled motor must reverse"
    tau = standard_regressor(model, q, qd, qdd, wrist_friction=form) @ chi
    work_in = cumulative_simpson(np.sum(tau * qd, axis=1), x=t, initial=0.0)
    dissipated = cumulative_simpson(friction_power(robot, chi, qd, form), x=t, initial=0.0)
    offsets = np.array([p(robot, chi, f"OFF{j + 1}") for j in range(robot.n)])
    offset_work = (q - q[0]) @ offsets
    energy = link_energy(model, chi, q, qd) + rotor_energy(robot, chi, qd)
    residual = work_in - dissipated - offset_work - (energy - energy[0])
    scale = cumulative_simpson(np.sum(np.abs(tau * qd), axis=1), x=t, initial=0.0)[-1]
    assert scale > 10.0  # J: the trajectory does real work
    tolerance = 1e-8 * scale
    assert np.max(np.abs(residual)) < tolerance

    if robot.couplings:  # the balance notices a wrong rotor model
        naive = link_energy(model, chi, q, qd) + rotor_energy(robot, chi, qd, coupled=False)
        wrong = work_in - dissipated - offset_work - (naive - naive[0])
        assert np.max(np.abs(wrong)) > 1e3 * tolerance
