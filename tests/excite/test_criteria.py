"""Criteria: values against plain numpy, gradients against finite differences, the WTLS null
vector against the regrouped base parameters."""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.config import load_payload, load_robot, load_truth, resource_path
from drivegain.dynamics.base import random_states
from drivegain.dynamics.model import build_model
from drivegain.dynamics.params import truth_vector
from drivegain.dynamics.regressor import stack_joint_major, standard_regressor
from drivegain.excite.criteria import (
    Criterion,
    base_criterion,
    design_currents,
    design_model,
    observation_matrix,
    wtls_criterion,
    wtls_design,
    wtls_matrix,
)
from drivegain.excite.optimise import ExcitationSettings, Problem


@pytest.fixture(scope="module")
def setup():
    robot = load_robot(resource_path("tx40.toml"))
    model = build_model(robot)
    design = design_model(model)
    payload = load_payload(resource_path("payloads/calibrated-4590g.toml"), robot.n)
    chi = truth_vector(robot, load_truth(resource_path("sim/tx40-truth.toml"), robot.n))
    return robot, model, design, payload, chi


def test_structurally_zero_columns_are_left_out(setup) -> None:
    _, model, design, _, _ = setup
    rng = np.random.default_rng(11)
    w = stack_joint_major(standard_regressor(model, *random_states(model, 150, rng)))
    norms = np.linalg.norm(w, axis=0)
    kept = set(design.kept.tolist())
    for k in design.base.base_index:
        if k in kept:
            assert norms[k] > 1e-6 * norms.max()
        else:
            assert norms[k] < 1e-12 * norms.max()
    # the base set (no zero column: base_parameters leaves them out) has full column rank
    a = w[:, design.kept]
    assert np.linalg.matrix_rank(a / np.linalg.norm(a, axis=0)) == design.n_kept


def test_cond_value_is_the_unit_column_condition_number(setup) -> None:
    _, model, design, _, _ = setup
    rng = np.random.default_rng(1)
    w = standard_regressor(model, *random_states(model, 60, rng))
    a = stack_joint_major(w)[:, design.kept]
    value, _ = base_criterion(design, w, "cond")
    assert np.exp(value) == pytest.approx(np.linalg.cond(a / np.linalg.norm(a, axis=0)), rel=1e-7)
    value, _ = base_criterion(design, w, "logdet")
    sign, logdet = np.linalg.slogdet(a.T @ a)
    assert sign > 0
    assert value == pytest.approx(-logdet / a.shape[1], rel=1e-9)


def _directional_check(fun, w: np.ndarray, rng: np.random.Generator) -> None:
    _, grad = fun(w)
    for _ in range(3):
        d = rng.normal(size=w.shape)
        d /= np.linalg.norm(d)
        eps = 1e-6 * np.linalg.norm(w)
        fd = (fun(w + eps * d)[0] - fun(w - eps * d)[0]) / (2 * eps)
        assert np.sum(grad * d) == pytest.approx(fd, rel=1e-4, abs=1e-8)


@pytest.mark.parametrize("criterion", list(Criterion))
def test_base_criterion_gradient(setup, criterion: Criterion) -> None:
    _, model, design, _, _ = setup
    rng = np.random.default_rng(2)
    w = standard_regressor(model, *random_states(model, 40, rng))
    _directional_check(lambda x: base_criterion(design, x, criterion), w, rng)


def test_wtls_criterion_gradient(setup) -> None:
    robot, model, design, payload, chi = setup
    rng = np.random.default_rng(3)
    w = standard_regressor(model, *random_states(model, 40, rng))
    wt = wtls_design(robot, chi, payload)
    _directional_check(lambda x: wtls_criterion(design, wt, x), w, rng)


def test_wtls_matrix_null_vector_is_the_paper_solution(setup) -> None:
    """Noise-free W_tot @ [chi_base, g, chi_uL, 1] = 0 (eq. 15), with chi_base regrouped by
    the identify package's base parameters."""
    robot, model, design, payload, chi = setup
    rng = np.random.default_rng(4)
    w = standard_regressor(model, *random_states(model, 80, rng))
    wt = wtls_design(robot, chi, payload)
    v_a, v_b = design_currents(design, wt, w)
    m = wtls_matrix(design, wt, w, v_a, w, v_b)
    base_values = dict(zip(design.base.base_index.tolist(), design.base.regroup(chi), strict=True))
    chi_base = np.array([base_values[k] for k in design.kept.tolist()])
    known = payload.known_mask()
    x = np.concatenate(
        [chi_base, robot.apriori_gains, np.nan_to_num(payload.values[~known]), [1.0]]
    )
    residual = np.linalg.norm(m @ x) / np.linalg.norm(np.abs(m) @ np.abs(x))
    assert residual < 1e-12
    assert m.shape == (2 * 80 * robot.n, design.n_kept + robot.n + 9 + 1)
    # The same for the base block alone: observation_matrix @ chi_base = torques.
    tau = stack_joint_major(w @ chi)
    np.testing.assert_allclose(observation_matrix(design, w) @ chi_base, tau, atol=1e-9)


def test_objective_gradient_in_the_coefficients(setup) -> None:
    """The chain rule through the regressor's state derivatives against plain differences."""
    robot, _, design, payload, chi = setup
    settings = ExcitationSettings(harmonics=2, payload=payload, chi_nominal=chi)
    prob = Problem(robot, settings, design=design)
    rng = np.random.default_rng(5)
    theta = prob.random_start(rng)
    value, grad = prob.value_and_grad(theta)
    assert value == pytest.approx(prob.value(theta), rel=1e-12)
    for _ in range(3):
        d = rng.normal(size=theta.shape)
        d /= np.linalg.norm(d)
        eps = 1e-6
        fd = (prob.value(theta + eps * d) - prob.value(theta - eps * d)) / (2 * eps)
        assert grad @ d == pytest.approx(fd, rel=2e-3, abs=1e-5)
