"""The simulated runs: torques against Pinocchio's RNEA, currents, quantisation, excitation."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from drivegain.config.robot import WristFriction
from drivegain.dynamics.params import to_pinocchio_order, with_payload
from drivegain.dynamics.transmission import joint_torque
from drivegain.identify.synth import quantise, scaled_sum_of_sines, simulate_run


def _reference_torque(world, q, qd, qdd, payload, form: WristFriction) -> np.ndarray:
    """Joint torques written from model.md directly: RNEA + rotor, friction, coupled wrist."""
    truth = world.truth
    model = world.model.pin_model.copy()
    data = model.createData()
    for j, link in enumerate(truth.links):
        p = np.concatenate([link.inertia, link.first_moment, [link.mass]])
        if payload is not None and payload.link == j + 1:
            p = p + payload.values
        model.inertias[j + 1] = pin.Inertia.FromDynamicParameters(to_pinocchio_order(p))
    tau = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k]) for k in range(q.shape[0])])
    for j, link in enumerate(truth.links):
        tau[:, j] += link.Ia * qdd[:, j] + link.Fv * qd[:, j] + link.Fc * np.sign(qd[:, j])
    # Motor 6 turns with q5 + q6: its inertia Ia6 acts on q5dd + q6dd in both rows (the
    # diagonal parts are in Ia5 and Ia6 already), its friction on the joint-5 and 6 rows.
    ia6 = truth.links[5].Ia
    tau[:, 4] += ia6 * qdd[:, 5] + truth.fvm * qd[:, 5]
    tau[:, 5] += ia6 * qdd[:, 4] + truth.fvm * qd[:, 4]
    s_sum = np.sign(qd[:, 4] + qd[:, 5])
    if form is WristFriction.PHYSICAL:
        tau[:, 4] += truth.fcm * s_sum
        tau[:, 5] += truth.fcm * s_sum
    else:
        tau[:, 4] += truth.fcm * np.sign(qd[:, 5])
        tau[:, 5] += truth.fcm * (s_sum - np.sign(qd[:, 5]))
    return tau


@pytest.mark.parametrize("form", list(WristFriction))
def test_simulated_torques_match_rnea(world, form: WristFriction) -> None:
    t = np.linspace(0.0, 5.0, 40)
    q, qd, qdd = world.excitations[0].evaluate(t)[:3]
    sim = simulate_run(world.model, world.truth, q, qd, qdd, payload=world.payload, friction=form)
    ref = _reference_torque(world, q, qd, qdd, world.payload, form)
    np.testing.assert_allclose(sim.tau_true, ref, atol=1e-9 * np.abs(ref).max())
    np.testing.assert_allclose(sim.tau, sim.tau_true, atol=1e-12 * np.abs(ref).max())  # no noise


def test_currents_carry_the_torques_and_the_noise(world) -> None:
    t = np.arange(0.0, 4.0, 0.002)
    q, qd, qdd = world.excitations[1].evaluate(t)[:3]
    rng = np.random.default_rng(3)
    sim = simulate_run(world.model, world.truth, q, qd, qdd, torque_noise=0.05, rng=rng)
    np.testing.assert_allclose(
        joint_torque(world.robot, sim.current_reference, world.truth.gains), sim.tau, atol=1e-9
    )
    noise = sim.tau - sim.tau_true
    np.testing.assert_allclose(noise.std(axis=0), 0.05, rtol=0.1)
    # Current noise enters through V (eq. 21): drive 6's noise reaches joint 5 as well.
    cur = simulate_run(world.model, world.truth, q, qd, qdd, current_noise=0.01, rng=rng)
    g = world.truth.gains
    expected = 0.01 * np.abs(g)
    expected[4] = 0.01 * np.hypot(g[4], g[5])
    np.testing.assert_allclose((cur.tau - cur.tau_true).std(axis=0), expected, rtol=0.1)
    # Unchanged payload: the true torques do not depend on the noise draw.
    other = simulate_run(world.model, world.truth, q, qd, qdd, torque_noise=0.05)
    np.testing.assert_array_equal(other.tau_true, sim.tau_true)


def test_quantise_rounds_to_a_grid() -> None:
    rng = np.random.default_rng(4)
    q = rng.uniform(-3, 3, size=(1000, 2))
    step = np.deg2rad(1e-3)
    qm = quantise(q, step, rng)
    assert np.abs(qm - q).max() <= step / 2 + 1e-15
    # Differences between readings are whole numbers of quanta.
    k = np.diff(qm[:, 0]) / step
    np.testing.assert_allclose(k, np.round(k), atol=1e-6)


def test_sum_of_sines_derivatives_and_limits(world) -> None:
    rng = np.random.default_rng(5)
    ex = scaled_sum_of_sines(world.robot, rng, base_frequency_hz=0.2, harmonics=5, margin=0.8)
    h = 1e-4
    t = np.linspace(0.0, 5.0, 5001)
    q, qd, qdd = ex.evaluate(t)[:3]
    qp, qdp, _ = ex.evaluate(t + h)[:3]
    qm, qdm, _ = ex.evaluate(t - h)[:3]
    np.testing.assert_allclose((qp - qm) / (2 * h), qd, atol=1e-6)
    np.testing.assert_allclose((qdp - qdm) / (2 * h), qdd, atol=1e-5)
    r = world.robot
    assert np.all(q >= r.lower) and np.all(q <= r.upper)
    assert np.all(np.abs(qd).max(axis=0) <= 0.8 * r.velocity_limits + 1e-9)
    assert np.all(np.abs(qdd).max(axis=0) <= 0.8 * r.acceleration_limits + 1e-9)
    # Periodic over one base period.
    np.testing.assert_allclose(ex.evaluate(np.array([5.0]))[0], q[:1], atol=1e-12)
    # with_payload is what the simulation adds for a payload.
    assert with_payload is not None
