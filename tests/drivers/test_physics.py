"""The simulator's physics against the identification model (the regressor) and basic mechanics."""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.config import load_payload, load_truth, resource_path
from drivegain.drivers.physics import (
    RECENT_STEPS,
    Dynamics,
    MotorMode,
    RobotPhysics,
    design_gains,
    truth_parameters,
)
from drivegain.dynamics.model import build_model
from drivegain.dynamics.regressor import standard_regressor


@pytest.fixture(scope="module")
def truth():
    return load_truth(resource_path("sim/tx40-truth.toml"))


@pytest.mark.parametrize("friction", ["physical", "paper"])
@pytest.mark.parametrize("with_payload", [False, True])
def test_dynamics_equal_the_regressor(tx40, truth, friction, with_payload):
    payload = (
        load_payload(resource_path("payloads/calibrated-4590g.toml")) if with_payload else None
    )
    chi = truth_parameters(tx40, truth, payload)
    dyn = Dynamics(tx40, chi, friction)
    model = build_model(tx40)
    rng = np.random.default_rng(5)
    q, qd, qdd = rng.uniform(-2.0, 2.0, (3, 20, 6))
    qd[0, 4] = -qd[0, 5]  # coupled motor at rest: sign(q5d + q6d) = 0
    expected = standard_regressor(model, q, qd, qdd, wrist_friction=friction) @ chi
    got = np.array([dyn.inverse(*x) for x in zip(q, qd, qdd, strict=True)])
    np.testing.assert_allclose(got, expected, atol=1e-10)
    # The mass matrix, column by column from the regressor with unit accelerations.
    zero = np.zeros((7, 6))
    columns = standard_regressor(
        model, np.repeat(q[:1], 7, 0), zero, np.vstack([zero[:1], np.eye(6)])
    )
    m_reg = (columns[1:] @ chi - columns[0] @ chi).T
    np.testing.assert_allclose(dyn.mass_matrix(q[0]), m_reg, atol=1e-12)
    assert m_reg[4, 5] == pytest.approx(m_reg[5, 4])  # rotor 6 couples joints 5 and 6


def make_physics(tx40, truth, noise=0.0, dt=0.0005, q0=None):
    chi = truth_parameters(tx40, truth)
    dyn = Dynamics(tx40, chi)
    q0 = np.zeros(6) if q0 is None else q0
    loop = design_gains(tx40, dyn, truth.gains, q0)
    return RobotPhysics(tx40, dyn, truth.gains, loop, dt, q0, noise, np.random.default_rng(0)), chi


def test_forward_dynamics_obey_the_inverse_model(tx40, truth):
    ph, chi = make_physics(tx40, truth, noise=0.5)
    for j in range(6):
        ph.set_mode(j, MotorMode.TRACK)
    model = build_model(tx40)
    k = tx40.transmission()
    for step in range(200):
        target = 0.3 * np.sin(np.arange(6) + step * 0.02)
        ph.latch_targets(k @ target, np.ones(6, bool), 0.004)
        out = ph.evaluate()
        tau = (standard_regressor(model, ph.q, ph.qd, out.qdd) @ chi)[0]
        np.testing.assert_allclose(out.tau, tau, atol=1e-9)
        # Motor torques (gain / ratio x current) reach the joints through K^T.
        np.testing.assert_allclose(out.tau, k.T @ (truth.gains / tx40.gear_ratios * out.current))
        ph.advance(8)


def test_a_braked_coupled_motor_holds_while_joint_5_moves(tx40, truth):
    ph, _ = make_physics(tx40, truth)
    k = tx40.transmission()
    for j in range(5):
        ph.set_mode(j, MotorMode.TRACK)  # motor 6 stays braked
    x6 = ph.motor_positions()[5]
    target = np.zeros(6)
    target[4] = 0.2
    ph.latch_targets(k @ target, np.arange(6) < 5, 0.2)
    ph.advance(2000)  # 1 s
    assert ph.q[4] == pytest.approx(0.2, abs=2e-3)
    # Motor 6 (K6 (q5 + q6)) did not turn, so joint 6 turned by -q5.
    assert ph.motor_positions()[5] == pytest.approx(x6, abs=1e-9)
    assert ph.q[5] == pytest.approx(-ph.q[4], abs=1e-9)


def test_quick_stop_ramps_to_rest(tx40, truth):
    ph, _ = make_physics(tx40, truth)
    for j in range(6):
        ph.set_mode(j, MotorMode.TRACK)
    k = tx40.transmission()
    for step in range(400):  # accelerate joint 1 to about 1 rad/s
        ph.latch_targets(k @ np.r_[0.004 * step, np.zeros(5)], np.ones(6, bool), 0.004)
        ph.advance(8)
    assert ph.qd[0] == pytest.approx(1.0, abs=0.05)
    ph.set_quick_stop_deceleration(np.full(6, 10.0 * 32))  # 10 rad/s² at joint 1
    for j in range(6):
        ph.set_mode(j, MotorMode.QUICK_STOP)
    steps = 0
    while not ph.quick_stop_done()[0]:
        ph.advance(1)
        steps += 1
    assert steps * ph.dt == pytest.approx(0.1, abs=0.01)  # 1 rad/s at 10 rad/s²
    assert abs(ph.qd[0]) < 0.05


def test_encoder_counts_are_quantised_motor_angles(tx40, truth):
    q0 = np.array([0.1, -0.2, 0.3, 0.4, -0.5, 0.6])
    ph, _ = make_physics(tx40, truth, q0=q0)
    counts = ph.encoder_counts()
    cpr = np.array([j.encoder_counts for j in tx40.joints])
    expected = np.rint(tx40.transmission() @ q0 * cpr / (2 * np.pi))
    np.testing.assert_array_equal(counts, expected)
    assert counts[5] == round(32 * (-0.5 + 0.6) * 65536 / (2 * np.pi))


def test_motor_state_at_a_past_instant_interpolates_the_steps_taken(tx40, truth):
    """What a drive latched at a SYNC its simulator thread handles late: the state then."""
    ph, _ = make_physics(tx40, truth)
    ph.keep_recent_steps()
    for j in range(6):
        ph.set_mode(j, MotorMode.TRACK)
    k = tx40.transmission()
    seen = {}
    for step in range(120):  # joint 1 accelerating: the state changes every step
        ph.latch_targets(k @ np.r_[0.001 * step**1.5, np.zeros(5)], np.ones(6, bool), 0.004)
        seen[ph.step_index] = (ph.motor_positions(), ph.motor_velocities())
        ph.advance(1)
    now = ph.time_s
    for back in (1, 7, 40):  # exactly on a step
        x, xd = ph.motor_state_at(now - back * ph.dt)
        np.testing.assert_allclose(x, seen[ph.step_index - back][0], atol=1e-12)
        np.testing.assert_allclose(xd, seen[ph.step_index - back][1], atol=1e-12)
    # between two steps: linear in time
    a, b = seen[ph.step_index - 11], seen[ph.step_index - 10]
    x, _ = ph.motor_state_at(now - 10.25 * ph.dt)
    np.testing.assert_allclose(x, 0.25 * a[0] + 0.75 * b[0], atol=1e-12)
    # now or later: the present state; older than the steps kept: the oldest kept
    np.testing.assert_array_equal(ph.motor_state_at(now + 1.0)[0], ph.motor_positions())
    oldest = ph.step_index - RECENT_STEPS
    np.testing.assert_allclose(ph.motor_state_at(0.0)[0], seen[oldest][0], atol=1e-12)
