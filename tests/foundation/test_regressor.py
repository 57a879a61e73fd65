"""The IDIM regressor against independent inverse dynamics (Pinocchio's RNEA plus drive terms).

The reference torques never go through :mod:`drivegain.dynamics.regressor`: the rigid body part is
``pin.rnea`` on a copy of the kinematic model whose link inertias are set from the parameter
vector, and the rotor-inertia, friction, offset and coupled-motor terms are written out below from
docs/model.md.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from drivegain.config import load_payload, load_robot, load_truth, resource_path
from drivegain.config.robot import Coupling, Robot, WristFriction
from drivegain.dynamics import regressor as reg
from drivegain.dynamics.model import RobotModel, build_model
from drivegain.dynamics.params import standard_names, truth_vector
from drivegain.errors import InputError

DATA = Path(__file__).resolve().parents[1] / "data"
INERTIAL = ("XX", "XY", "XZ", "YY", "YZ", "ZZ", "MX", "MY", "MZ", "M")
#: Pinocchio's dynamic-parameter order [m mx my mz Ixx Ixy Iyy Ixz Iyz Izz], as our names.
PIN_ORDER = ("M", "MX", "MY", "MZ", "XX", "XY", "YY", "XZ", "YZ", "ZZ")


# --------------------------------------------------------------------------- robots and vectors


@pytest.fixture(scope="module")
def tx40() -> RobotModel:
    return build_model(load_robot(resource_path("tx40.toml")))


@pytest.fixture(scope="module")
def arm4() -> RobotModel:
    return build_model(load_robot(DATA / "arm4.toml"))


def _col(robot: Robot) -> dict[str, int]:
    return {name: k for k, name in enumerate(standard_names(robot))}


def _random_body(rng: np.random.Generator) -> tuple[float, np.ndarray, np.ndarray]:
    """A physically consistent body: mass (kg), centre of mass (m), inertia at the CoM (kg·m²)."""
    mass = rng.uniform(0.3, 6.0)
    com = rng.uniform(-0.2, 0.2, 3)
    a, b = rng.uniform(0.005, 0.05, 2)
    principal = np.array([a, b, rng.uniform(abs(a - b), a + b)])  # triangle inequality
    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return mass, com, rot @ np.diag(principal) @ rot.T


def _inertial_at_origin(mass: float, com: np.ndarray, inertia_c: np.ndarray) -> dict[str, float]:
    """The 10 standard inertial parameters of a body (parallel-axis theorem written out)."""
    c = np.asarray(com)
    i_o = inertia_c + mass * (c @ c * np.eye(3) - np.outer(c, c))
    mc = mass * c
    return {
        "XX": i_o[0, 0],
        "XY": i_o[0, 1],
        "XZ": i_o[0, 2],
        "YY": i_o[1, 1],
        "YZ": i_o[1, 2],
        "ZZ": i_o[2, 2],
        "MX": mc[0],
        "MY": mc[1],
        "MZ": mc[2],
        "M": mass,
    }


def random_chi(robot: Robot, rng: np.random.Generator) -> np.ndarray:
    """A random standard vector: consistent links, positive drive terms, signed offsets."""
    col = _col(robot)
    chi = np.zeros(len(col))
    for j in range(robot.n):
        for name, value in _inertial_at_origin(*_random_body(rng)).items():
            chi[col[f"{name}{j + 1}"]] = value
        chi[col[f"Ia{j + 1}"]] = rng.uniform(0.01, 0.5)
        chi[col[f"Fv{j + 1}"]] = rng.uniform(0.1, 8.0)
        chi[col[f"Fc{j + 1}"]] = rng.uniform(0.1, 8.0)
        chi[col[f"OFF{j + 1}"]] = rng.uniform(-2.0, 2.0)
    for c in robot.couplings:
        chi[col[f"fvm{c.motor + 1}"]] = rng.uniform(0.1, 2.0)
        chi[col[f"fcm{c.motor + 1}"]] = rng.uniform(0.1, 3.0)
    return chi


def random_states(
    robot: Robot, samples: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint positions over (beyond) the range, signed velocities and accelerations."""
    q = rng.uniform(-np.pi, np.pi, (samples, robot.n))
    qd = rng.uniform(-1.0, 1.0, (samples, robot.n)) * robot.velocity_limits
    qdd = rng.uniform(-1.0, 1.0, (samples, robot.n)) * robot.acceleration_limits
    qd[0, :] = 0.0  # sign(0) = 0 on every Coulomb term
    if robot.couplings and samples > 1:
        c = robot.couplings[0]
        qd[1, c.joint] = -qd[1, c.motor]  # the coupled motor at rest, its joints not
    return q, qd, qdd


# --------------------------------------------------------------------------- the reference


def pin_model_with(model: RobotModel, chi: np.ndarray) -> pin.Model:
    """A copy of the kinematic model carrying the link inertias of ``chi``."""
    col = _col(model.robot)
    pm = pin.Model(model.pin_model)
    for j in range(model.n):
        dyn = np.array([chi[col[f"{name}{j + 1}"]] for name in PIN_ORDER])
        pm.inertias[j + 1] = pin.Inertia.FromDynamicParameters(dyn)
    return pm


def drive_terms(
    robot: Robot, chi: np.ndarray, qd: np.ndarray, qdd: np.ndarray, form: WristFriction
) -> np.ndarray:
    """Rotor inertia, friction, offsets and coupled-motor torques (N·m), from docs/model.md.

    Every joint: ``Ia q̈ + Fv q̇ + Fc sign(q̇) + OFF``. A motor m coupled to joint o (TX-40: motor 6
    turns with q5 + q6) adds, in the ``physical`` form, ``Ia_m q̈_m + fvm q̇_m + fcm sign(q̇_o + q̇_m)``
    to row o and ``Ia_m q̈_o + fvm q̇_o + fcm sign(q̇_o + q̇_m)`` to row m; in the ``paper`` form
    (eq. 22 as printed) the Coulomb parts are ``fcm sign(q̇_m)`` on row o and
    ``fcm (sign(q̇_o + q̇_m) - sign(q̇_m))`` on row m.
    """
    col = _col(robot)
    tau = np.zeros_like(qd)
    for j in range(robot.n):
        p = lambda name, j=j: chi[col[f"{name}{j + 1}"]]  # noqa: E731
        tau[:, j] = (
            p("Ia") * qdd[:, j] + p("Fv") * qd[:, j] + p("Fc") * np.sign(qd[:, j]) + p("OFF")
        )
    for c in robot.couplings:
        m, o = c.motor, c.joint
        ia, fvm, fcm = chi[col[f"Ia{m + 1}"]], chi[col[f"fvm{m + 1}"]], chi[col[f"fcm{m + 1}"]]
        s_motor = np.sign(qd[:, o] + qd[:, m])
        tau[:, o] += ia * qdd[:, m] + fvm * qd[:, m]
        tau[:, m] += ia * qdd[:, o] + fvm * qd[:, o]
        if form is WristFriction.PHYSICAL:
            tau[:, o] += fcm * s_motor
            tau[:, m] += fcm * s_motor
        else:
            tau[:, o] += fcm * np.sign(qd[:, m])
            tau[:, m] += fcm * (s_motor - np.sign(qd[:, m]))
    return tau


def inverse_dynamics(
    model: RobotModel,
    chi: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    form: WristFriction,
) -> np.ndarray:
    """Joint torques (N·m), shape (N, n), without the regressor."""
    pm = pin_model_with(model, chi)
    data = pm.createData()
    rigid = np.array([pin.rnea(pm, data, q[k], qd[k], qdd[k]) for k in range(len(q))])
    return rigid + drive_terms(model.robot, chi, qd, qdd, form)


# --------------------------------------------------------------------------- tests

CASES = [("tx40", WristFriction.PHYSICAL), ("tx40", WristFriction.PAPER), ("arm4", None)]


@pytest.fixture(params=CASES, ids=["tx40-physical", "tx40-paper", "arm4"])
def case(request: pytest.FixtureRequest) -> tuple[RobotModel, WristFriction]:
    """A model of :data:`CASES` (a fixture's name) and its friction form (default the robot's)."""
    name, form = request.param
    model = request.getfixturevalue(name)
    return model, form or model.robot.wrist_friction


def test_tx40_is_the_coupled_wrist(tx40: RobotModel) -> None:
    assert tx40.robot.couplings == (Coupling(motor=5, joint=4),)
    assert len(standard_names(tx40.robot)) == 86


def test_regressor_times_chi_equals_rnea_plus_drive_terms(
    case: tuple[RobotModel, WristFriction],
) -> None:
    model, form = case
    rng = np.random.default_rng(11)
    # More samples than one internal chunk, and not a multiple of it.
    q, qd, qdd = random_states(model.robot, 2 * reg.CHUNK + 37, rng)
    w = reg.standard_regressor(model, q, qd, qdd, wrist_friction=form)
    assert w.shape == (len(q), model.n, len(standard_names(model.robot)))
    for _ in range(3):
        chi = random_chi(model.robot, rng)
        expected = inverse_dynamics(model, chi, q, qd, qdd, form)
        np.testing.assert_allclose(w @ chi, expected, rtol=0.0, atol=1e-9)


def test_tx40_truth_and_urdf_inertias(tx40: RobotModel, arm4: RobotModel) -> None:
    """The shipped TX-40 truth, and arm4 with the inertias of its URDF (fixed tool merged)."""
    rng = np.random.default_rng(5)
    truth = truth_vector(tx40.robot, load_truth(resource_path("sim/tx40-truth.toml")))
    q, qd, qdd = random_states(tx40.robot, 40, rng)
    w = reg.standard_regressor(tx40, q, qd, qdd)
    ref = inverse_dynamics(tx40, truth, q, qd, qdd, WristFriction.PHYSICAL)
    np.testing.assert_allclose(w @ truth, ref, rtol=0.0, atol=1e-9)

    pm = arm4.pin_model
    data = pm.createData()
    col = _col(arm4.robot)
    chi = np.zeros(len(col))
    for j in range(arm4.n):
        dyn = pm.inertias[j + 1].toDynamicParameters()
        for name, value in zip(PIN_ORDER, dyn, strict=True):
            chi[col[f"{name}{j + 1}"]] = value
    assert chi[col["M4"]] == pytest.approx(0.7 + 0.4)  # the tool is part of link 4
    q, qd, qdd = random_states(arm4.robot, 40, rng)
    w = reg.standard_regressor(arm4, q, qd, qdd)
    ref = np.array([pin.rnea(pm, data, q[k], qd[k], qdd[k]) for k in range(len(q))])
    np.testing.assert_allclose(w @ chi, ref, rtol=0.0, atol=1e-9)


def test_regressor_is_the_jacobian_of_the_inverse_dynamics(
    case: tuple[RobotModel, WristFriction],
) -> None:
    model, form = case
    rng = np.random.default_rng(3)
    q, qd, qdd = random_states(model.robot, 4, rng)
    chi = random_chi(model.robot, rng)
    h = 1e-3
    jac = np.empty((len(q), model.n, len(chi)))
    for k in range(len(chi)):
        step = np.zeros_like(chi)
        step[k] = h
        plus = inverse_dynamics(model, chi + step, q, qd, qdd, form)
        minus = inverse_dynamics(model, chi - step, q, qd, qdd, form)
        jac[:, :, k] = (plus - minus) / (2 * h)
    w = reg.standard_regressor(model, q, qd, qdd, wrist_friction=form)
    np.testing.assert_allclose(w, jac, rtol=0.0, atol=1e-8)


@pytest.mark.parametrize("name", ["tx40", "arm4"])
def test_rigid_part_equals_pinocchio_regressor(request: pytest.FixtureRequest, name: str) -> None:
    model = request.getfixturevalue(name)
    n = model.n
    rng = np.random.default_rng(7)
    q, qd, qdd = random_states(model.robot, 30, rng)
    data = model.pin_model.createData()
    y_pin = np.array(
        [
            pin.computeJointTorqueRegressor(model.pin_model, data, q[k], qd[k], qdd[k])
            for k in range(len(q))
        ]
    )
    # Pinocchio's per-body columns [m mx my mz Ixx Ixy Iyy Ixz Iyz Izz] into our order.
    perm = [PIN_ORDER.index(p) for p in INERTIAL]
    y_ours_order = y_pin.reshape(len(q), n, n, 10)[..., perm].reshape(len(q), n, 10 * n)
    rigid = reg.rigid_body_regressor(model, q, qd, qdd)
    np.testing.assert_allclose(rigid, y_ours_order, rtol=0.0, atol=1e-10)
    std = reg.standard_regressor(model, q, qd, qdd)
    for j in range(n):
        np.testing.assert_array_equal(
            std[:, :, 14 * j : 14 * j + 10], rigid[:, :, 10 * j : 10 * j + 10]
        )


def test_payload_columns_give_the_payload_torque(tx40: RobotModel) -> None:
    """A payload fixed to link 6: its torque is W[..., payload_columns] @ its 10 parameters."""
    payload = load_payload(resource_path("payloads/calibrated-4590g.toml"))
    values = np.nan_to_num(payload.values, nan=0.0)
    rng = np.random.default_rng(2)
    q, qd, qdd = random_states(tx40.robot, 20, rng)
    w = reg.standard_regressor(tx40, q, qd, qdd)
    cols = reg.payload_columns(tx40, payload.link)
    pm = pin.Model(tx40.pin_model)
    data = pm.createData()
    dyn = np.array([values[INERTIAL.index(p)] for p in PIN_ORDER])
    pm.inertias[payload.link] = pin.Inertia.FromDynamicParameters(dyn)
    ref = np.array([pin.rnea(pm, data, q[k], qd[k], qdd[k]) for k in range(len(q))])
    np.testing.assert_allclose(w[:, :, cols] @ values, ref, rtol=0.0, atol=1e-9)


def test_single_sample_and_shapes(tx40: RobotModel) -> None:
    rng = np.random.default_rng(4)
    q, qd, qdd = random_states(tx40.robot, 3, rng)
    all_at_once = reg.standard_regressor(tx40, q, qd, qdd)
    for k in range(3):
        one = reg.standard_regressor(tx40, q[k], qd[k], qdd[k])
        assert one.shape == (1, 6, 86)
        np.testing.assert_allclose(one[0], all_at_once[k], rtol=0.0, atol=1e-12)
    assert reg.standard_regressor(tx40, q[:0], qd[:0], qdd[:0]).shape == (0, 6, 86)
    with pytest.raises(InputError, match="qd must have shape"):
        reg.standard_regressor(tx40, q, qd[:, :5], qdd)
    with pytest.raises(InputError, match="same number of samples"):
        reg.standard_regressor(tx40, q[:2], qd, qdd)


def test_stack_joint_major() -> None:
    x = np.arange(2 * 3 * 4).reshape(2, 3, 4)
    stacked = reg.stack_joint_major(x)
    # Rows: joint 0 of samples 0, 1, then joint 1 of samples 0, 1, ...
    expected = np.array([x[s, j] for j in range(3) for s in range(2)])
    np.testing.assert_array_equal(stacked, expected)
    np.testing.assert_array_equal(reg.stack_joint_major(x[:, :, 0]), expected[:, 0])
    with pytest.raises(InputError, match="2-D or 3-D"):
        reg.stack_joint_major(np.zeros(3))


def test_concurrent_calls_agree(tx40: RobotModel) -> None:
    """Threads share the cached work arrays only one at a time (others get a private one)."""
    rng = np.random.default_rng(9)
    states = [random_states(tx40.robot, 700, rng) for _ in range(6)]
    expected = [reg.standard_regressor(tx40, *s) for s in states]
    with ThreadPoolExecutor(max_workers=3) as pool:
        got = list(pool.map(lambda s: reg.standard_regressor(tx40, *s), states))
    for e, g in zip(expected, got, strict=True):
        np.testing.assert_array_equal(g, e)


def test_half_angle_sin_cos_matches_numpy() -> None:
    """The regressor's sine and cosine (from tan(q/2)) against numpy's, over and beyond ±π."""
    q = np.concatenate(
        [
            np.linspace(-4.8, 4.8, 200_001),
            np.pi * np.array([1.0, -1.0, 0.5, -0.5, 0.0]),
            np.nextafter(np.pi, 0.0) * np.array([1.0, -1.0]),
        ]
    )
    sin, cos = np.empty_like(q), np.empty_like(q)
    reg._sin_cos(q.copy(), sin, cos)
    np.testing.assert_allclose(sin, np.sin(q), rtol=0.0, atol=3e-16)
    np.testing.assert_allclose(cos, np.cos(q), rtol=0.0, atol=3e-16)


def test_output_is_fresh_and_not_held(tx40: RobotModel) -> None:
    """Each call returns its own array; the cached kernel keeps no view of it."""
    rng = np.random.default_rng(4)
    q, qd, qdd = random_states(tx40.robot, reg.CHUNK + 5, rng)
    a = reg.standard_regressor(tx40, q, qd, qdd)
    b = reg.standard_regressor(tx40, q, qd, qdd)
    assert not np.shares_memory(a, b)
    np.testing.assert_array_equal(a, b)
    a[...] = np.nan  # writable, and writing it changes nothing the next call sees
    np.testing.assert_array_equal(reg.standard_regressor(tx40, q, qd, qdd), b)
    # Another last-chunk width (its binding is cached), then the first one again.
    q9, qd9, qdd9 = random_states(tx40.robot, reg.CHUNK + 9, rng)
    c = reg.standard_regressor(tx40, q9, qd9, qdd9)
    np.testing.assert_array_equal(reg.standard_regressor(tx40, q, qd, qdd), b)
    np.testing.assert_array_equal(reg.standard_regressor(tx40, q9[:7], qd9[:7], qdd9[:7]), c[:7])
    for store in reg._CACHE.values():
        for key, kern in store[1].items():
            if key[0] == "kernel" and kern._full is not None:
                held = [*kern._full[1], *kern._part[1][1]]
                assert all(args[pos] is None for args, pos, _ in held)
