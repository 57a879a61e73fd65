"""The shipped TX-40 trajectory (``config/tx40-excitation.json``, the real optimised one):
cond below 60, better than random feasible trajectories, and a clearly larger WTLS gap on
simulated data. Everything here is recomputed with the identify package and numpy only."""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.config import load_payload, load_robot, load_truth, resource_path
from drivegain.dynamics.base import base_parameters, random_states
from drivegain.dynamics.model import build_model
from drivegain.dynamics.params import inertial_slice, truth_vector, with_payload
from drivegain.dynamics.regressor import stack_joint_major, standard_regressor
from drivegain.dynamics.transmission import current_matrix, currents_for_torque
from drivegain.excite.limits import ExcitationLimits
from drivegain.excite.optimise import ExcitationSettings, Problem, random_trajectory
from drivegain.excite.trajectory import load_trajectory
from drivegain.formats.fourier import FourierTrajectory

SAMPLES = 1000
N_RANDOM = 12


@pytest.fixture(scope="module")
def env():
    robot = load_robot(resource_path("tx40.toml"))
    model = build_model(robot)
    bp = base_parameters(model)
    rng = np.random.default_rng(99)
    w = stack_joint_major(standard_regressor(model, *random_states(model, 200, rng)))
    norms = np.linalg.norm(w[:, bp.base_index], axis=0)
    # Base columns that are identically zero (MZ2 of the TX-40) carry no information.
    cols = bp.base_index[norms > 1e-9 * norms.max()]
    shipped = load_trajectory(resource_path("tx40-excitation.json"))
    problem = Problem(robot, ExcitationSettings())
    randoms = [random_trajectory(problem, np.random.default_rng([7, i])) for i in range(N_RANDOM)]
    return robot, model, cols, shipped, randoms


def regressor(model, f: FourierTrajectory) -> np.ndarray:
    t = np.arange(SAMPLES) * f.period_s / SAMPLES
    q, qd, qdd, _ = f.evaluate(t)
    return standard_regressor(model, q, qd, qdd)


def cond(model, cols, f: FourierTrajectory) -> float:
    a = stack_joint_major(regressor(model, f))[:, cols]
    return float(np.linalg.cond(a / np.linalg.norm(a, axis=0)))


def test_file_is_the_tx40_default(env) -> None:
    robot, _, _, shipped, _ = env
    assert shipped.robot == robot.name and shipped.joint_names == robot.joint_names
    f = shipped.fourier
    assert (f.base_frequency_hz, f.harmonics, f.periods) == (0.1, 5, 3)
    assert shipped.extra["optimisation"]["payload"] == "calibrated-4590g"
    lim = ExcitationLimits.from_robot(robot)
    assert shipped.limits is not None
    np.testing.assert_allclose(shipped.limits.upper, lim.upper)
    np.testing.assert_allclose(shipped.limits.jerk, lim.jerk)


def test_cond_below_60_and_better_than_random(env) -> None:
    _, model, cols, shipped, randoms = env
    c = cond(model, cols, shipped.fourier)
    assert c == pytest.approx(shipped.metrics["cond"], rel=1e-6)
    random_conds = np.array([cond(model, cols, f) for f in randoms])
    print(
        f"\ncond (unit-norm columns): optimised {c:.3g}; {N_RANDOM} random feasible: median "
        f"{np.median(random_conds):.3g}, best {random_conds.min():.3g}, worst "
        f"{random_conds.max():.3g}"
    )
    assert c < 60
    assert c < random_conds.min()
    assert c < 0.2 * np.median(random_conds)


def wtls_gap(robot, model, cols, f: FourierTrajectory, rng: np.random.Generator) -> float:
    """s_(p-1)/s_p of the unit-column W_tot of an unloaded and a loaded run simulated along
    ``f``: true dynamics, true gains, current noise 0.2 % of the rated currents."""
    truth = load_truth(resource_path("sim/tx40-truth.toml"), robot.n)
    payload = load_payload(resource_path("payloads/calibrated-4590g.toml"), robot.n)
    chi = truth_vector(robot, truth)
    chi_b = with_payload(robot, chi, payload)
    w = regressor(model, f)
    rated = np.array([j.rated_current for j in robot.joints])
    currents = []
    for c in (chi, chi_b):
        v = currents_for_torque(robot, w @ c, truth.gains)
        currents.append(v + rng.normal(size=v.shape) * 0.002 * rated)
    a = stack_joint_major(w)[:, cols]
    sl = inertial_slice(payload.link - 1)
    pcols = np.arange(sl.start, sl.stop)
    known = payload.known_mask()
    w_ul = stack_joint_major(w[:, :, pcols[~known]])
    w_kl = stack_joint_major(w[:, :, pcols[known]] @ payload.values[known])[:, None]
    zeros = np.zeros_like(w_ul)
    v_a, v_b = (stack_joint_major(current_matrix(robot, v)) for v in currents)
    w_tot = np.block([[-a, v_a, zeros, 0 * w_kl], [-a, v_b, -w_ul, -w_kl]])
    s = np.linalg.svd(w_tot / np.linalg.norm(w_tot, axis=0), compute_uv=False)
    return float(s[-2] / s[-1])


def test_clearly_larger_wtls_gap_than_random(env) -> None:
    robot, model, cols, shipped, randoms = env
    rng = np.random.default_rng(2024)
    opt = wtls_gap(robot, model, cols, shipped.fourier, rng)
    rnd = np.array([wtls_gap(robot, model, cols, f, rng) for f in randoms[:6]])
    print(
        f"\nWTLS s(p-1)/s(p) on simulated data: optimised {opt:.3g}; random feasible "
        f"{np.array2string(rnd, precision=3)}"
    )
    assert opt > 3.0 * rnd.max()


def test_loaded_run_excites_joint_1(env) -> None:
    robot, model, _, shipped, _ = env
    payload = load_payload(resource_path("payloads/calibrated-4590g.toml"), robot.n)
    w = regressor(model, shipped.fourier)
    tau = w[:, :, inertial_slice(payload.link - 1)] @ payload.values
    rms = np.sqrt(np.mean(tau**2, axis=0))
    # joint 1 feels the payload only through inertia: it must still be a sizeable part of the
    # payload torques (N·m), not lost in friction.
    assert rms[0] > 0.3 * rms.max() and rms[0] > 3.0
    np.testing.assert_allclose(rms, shipped.metrics["payload_torque_rms"], rtol=1e-6)
