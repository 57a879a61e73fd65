"""The alternative gain estimators of drivegain.identify.compare on noise-free data.

The reference is the simulation truth: on exact data (no noise, exact derivatives) every
estimator whose model is right must return the true gains; those whose model is wrong (a
diagonal current matrix on the coupled wrist) must not.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from drivegain.config.payload import PAYLOAD_PARAMS
from drivegain.errors import IdentificationError, InputError
from drivegain.identify.compare import (
    _solve_order,
    coverage,
    diagonal_design,
    global_ls_gains,
    per_joint_gains,
    tls_gains,
    wtls_gains,
)
from drivegain.identify.design import Design, coupling_factor, make_design
from drivegain.identify.prepare import PreparedRun
from drivegain.validation.world import World

RATE = 10.0  # Hz: exact derivatives need no filter, so few samples suffice


@pytest.fixture(scope="module")
def exact(world: World, simulate_exact: Callable[..., PreparedRun]) -> tuple[Design, Design]:
    """Runs a and b along the shipped excitation, noise-free, exact derivatives."""
    t = np.arange(0.0, world.fourier.duration_s, 1.0 / RATE)
    q, qd, qdd, _ = world.fourier.evaluate(t)
    designs = []
    for label, payload in (("unloaded", None), ("loaded", world.payload)):
        run = simulate_exact(
            world.model, world.truth, world.columns, t, q, qd, qdd, label=label, payload=payload
        )
        designs.append(make_design(run, world.base, world.form, world.robot))
    return designs[0], designs[1]


def test_coupled_estimators_return_the_true_gains(world: World, exact: Any) -> None:
    a, b = exact
    g = world.truth.gains
    estimates = [
        wtls_gains(a, b, world.payload, world.robot.apriori_gains),
        tls_gains(a, b, world.payload),
        per_joint_gains(a, b, world.payload, known=PAYLOAD_PARAMS),
        global_ls_gains(a, b, world.payload),
    ]
    for est in estimates:
        assert est.coupled
        np.testing.assert_allclose(est.gains, g, rtol=1e-7, err_msg=est.method)


def test_diagonal_current_matrix_misses_the_coupled_gain(world: World, exact: Any) -> None:
    """Without g6·v6 in joint 5's equation, g5 is wrong; the global TLS spreads the error."""
    a, b = (diagonal_design(d) for d in exact)
    g = world.truth.gains
    tls = tls_gains(a, b, world.payload)
    assert not tls.coupled
    err = np.abs(tls.gains / g - 1.0)
    assert err[4] > 0.10 and err[5] > 0.10
    # Per joint, only joint 5's own equations are wrong.
    pj = per_joint_gains(a, b, world.payload, known=PAYLOAD_PARAMS)
    err = np.abs(pj.gains / g - 1.0)
    assert err[4] > 0.10
    np.testing.assert_allclose(np.delete(pj.gains, 4), np.delete(g, 4), rtol=1e-7)


def test_per_joint_with_the_mass_only_cannot_scale_the_wrist(world: World, exact: Any) -> None:
    """The payload sits at the wrist centre, on the axes of joints 4-6: its mass exerts no
    torque there (its column is zero in those rows), so those gains have no scale."""
    a, b = exact
    mass_col = b.nb + PAYLOAD_PARAMS.index("M")
    for j in (3, 4, 5):
        assert np.abs(b.block(j)[:, mass_col]).max() < 1e-9
    with pytest.raises(IdentificationError, match=r"joint 4: the known payload parameters \(M\)"):
        per_joint_gains(a, b, world.payload)
    with pytest.raises(InputError, match="unknown payload parameters"):
        per_joint_gains(a, b, world.payload, known=["mass"])


def test_estimators_refuse_swapped_runs(world: World, exact: Any) -> None:
    a, b = exact
    for fn in (tls_gains, global_ls_gains):
        with pytest.raises(IdentificationError, match="unloaded"):
            fn(b, a, world.payload)


def test_coupled_joint_is_solved_after_its_coupled_motor(world: World) -> None:
    order = _solve_order(coupling_factor(world.robot))
    assert sorted(order) == list(range(6))
    assert order.index(5) < order.index(4)  # joint 6 before joint 5 on the TX-40
    with pytest.raises(IdentificationError, match="cycle"):
        _solve_order(np.array([[1.0, 1.0], [1.0, 1.0]]))


def test_coverage_counts_intervals_holding_the_truth() -> None:
    est = [np.array([0.0, 1.0]), np.array([3.0, -1.9]), np.array([1.0, 2.5])]
    std = [np.ones(2)] * 3
    np.testing.assert_allclose(coverage(est, std, np.zeros(2)), [2 / 3, 2 / 3])
