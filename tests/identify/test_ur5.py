"""A second robot, the UR5 (no coupled joints, gear ratio 101, no a priori gains): its
description checked against the maker's DH table, and IDIM-WTLS within 1 % of its true gains
(issue 16, "a second robot")."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from drivegain.config import load_payload, load_robot, load_truth, resource_path
from drivegain.config.robot import WristFriction
from drivegain.dynamics.model import build_model
from drivegain.identify.columns import bases_for_forms, stored_columns
from drivegain.identify.prepare import prepare_recording
from drivegain.identify.procedure import Options, Problem, run_procedure
from drivegain.identify.signal import default_filter
from drivegain.identify.synth import exciting_sum_of_sines, simulate_run

# The maker's standard DH table of the UR5 (Universal Robots support article).
DH_A = [0.0, -0.425, -0.39225, 0.0, 0.0, 0.0]
DH_D = [0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823]
DH_ALPHA = [np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0]


def _dh_tool(q: np.ndarray) -> np.ndarray:
    """Flange pose by the maker's standard DH: Rz(θ) Tz(d) Tx(a) Rx(α) per joint."""
    t = np.eye(4)
    for th, d, a, al in zip(q, DH_D, DH_A, DH_ALPHA, strict=True):
        ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(al), np.sin(al)
        t = t @ np.array(
            [
                [ct, -st * ca, st * sa, a * ct],
                [st, ct * ca, -ct * sa, a * st],
                [0.0, sa, ca, d],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
    return t


@pytest.fixture(scope="module")
def ur5():
    robot = load_robot(resource_path("ur5.toml"))
    return robot, build_model(robot), load_truth(resource_path("sim/ur5-truth.toml"), robot.n)


def test_ur5_kinematics_match_the_makers_dh_table(ur5) -> None:
    robot, model, _ = ur5
    assert robot.couplings == () and np.all(robot.gear_ratios == 101.0)
    np.testing.assert_array_equal(robot.apriori_gains, robot.gear_ratios)  # none in the file
    data = model.pin_model.createData()
    rng = np.random.default_rng(0)
    for q in [np.zeros(6), *rng.uniform(-np.pi, np.pi, (5, 6))]:
        pin.forwardKinematics(model.pin_model, data, q)
        m = data.oMi[6]
        want = _dh_tool(q)  # DH frame 6 = MDH frame 6 (a6 = α6 = 0)
        np.testing.assert_allclose(m.translation, want[:3, 3], atol=1e-12)
        np.testing.assert_allclose(m.rotation, want[:3, :3], atol=1e-12)
    # The maker's zero: arm stretched along −x, flange at (a2 + a3, −(d4 + d6), d1 − d5).
    np.testing.assert_allclose(
        _dh_tool(np.zeros(6))[:3, 3], [-0.81725, -0.19145, -0.005491], atol=1e-12
    )


def test_ur5_gains_within_one_percent(ur5) -> None:
    robot, model, truth = ur5
    bases = bases_for_forms(model)
    assert len(bases) == 2 and bases[WristFriction.PHYSICAL] is bases[WristFriction.PAPER]
    payload = load_payload(resource_path("payloads/calibrated-4590g.toml"), robot.n)
    columns = stored_columns(robot, bases, [payload.link])
    rng = np.random.default_rng(5)
    rate, base_hz, harmonics = 250.0, 0.2, 5
    runs = []
    for label, pay in (("unloaded", None), ("loaded", payload)):
        traj = exciting_sum_of_sines(
            model, rng, base_frequency_hz=base_hz, harmonics=harmonics, candidates=8,
            base=bases[WristFriction.PHYSICAL],
        )  # fmt: skip
        t = np.arange(0.0, 30.0, 1 / rate)
        q, qd, qdd = traj.evaluate(t)[:3]
        sim = simulate_run(
            model, truth, q, qd, qdd, payload=pay, torque_noise=0.05,
            quantum=2 * np.pi / 65536 / 101, rng=rng,
        )  # fmt: skip
        runs.append(
            prepare_recording(
                model, columns, label=label, q=sim.q, current=sim.current_reference,
                rate_hz=rate, settings=default_filter(rate, base_hz * harmonics), payload=pay,
                period_s=1 / base_hz,
            )
        )  # fmt: skip
    problem = Problem(robot=robot, bases=bases, unloaded=runs[0], loaded=runs[1])
    result = run_procedure(problem, Options(friction=WristFriction.PHYSICAL))
    err = result.gains / truth.gains - 1
    assert np.all(np.abs(err) < 0.01), err
    assert result.gains_std is not None and np.all(result.gains_std / result.gains < 0.01)
    assert len(result.forms) == 1  # no coupled wrist: no friction-form comparison
    mass = result.final.payloads[0].values[9]
    assert mass == pytest.approx(4.59, rel=0.02)
