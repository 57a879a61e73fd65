"""The Fourier series: contracts §6 formula, derivatives, bounds, rigorous limit usage."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivegain.config import load_robot, resource_path
from drivegain.errors import TrajectoryError
from drivegain.excite.limits import ExcitationLimits, fourier_usage
from drivegain.formats.fourier import FourierTrajectory, basis, derivative_bounds, start_state


def random_series(seed: int, n: int = 3, h: int = 4, f: float = 0.2) -> FourierTrajectory:
    rng = np.random.default_rng(seed)
    return FourierTrajectory(
        f, rng.normal(size=n), rng.normal(size=(n, h)), rng.normal(size=(n, h)), periods=2
    )


def test_position_follows_the_contract_formula() -> None:
    f = random_series(1)
    t = np.linspace(-3.0, 13.0, 257)
    w = 2 * np.pi * f.base_frequency_hz
    expected = np.zeros((t.size, f.n))
    for j in range(f.n):
        expected[:, j] = f.q0[j]
        for ell in range(1, f.harmonics + 1):
            a, b = f.a[j, ell - 1], f.b[j, ell - 1]
            expected[:, j] += a / (w * ell) * np.sin(w * ell * t) - b / (w * ell) * np.cos(
                w * ell * t
            )
    q, *_ = f.evaluate(t)
    np.testing.assert_allclose(q, expected, atol=1e-12)


def test_derivatives_match_numerical_differentiation() -> None:
    f = random_series(2)
    t = np.linspace(0.0, 5.0, 41)
    h = 1e-4
    values = [np.stack(f.evaluate(t + d)) for d in (-h, 0.0, h)]
    numeric = (values[2] - values[0]) / (2 * h)  # derivative of q, qd, qdd, qddd
    for k in range(3):
        np.testing.assert_allclose(values[1][k + 1], numeric[k], rtol=1e-6, atol=1e-6)
    # Orders 4 and 5 of the basis, also against differences.
    for k in (4, 5):
        b_lo = basis(t - h, f.omega, f.harmonics, k - 1)
        b_hi = basis(t + h, f.omega, f.harmonics, k - 1)
        np.testing.assert_allclose(
            basis(t, f.omega, f.harmonics, k), (b_hi - b_lo) / (2 * h), rtol=1e-5, atol=1e-5
        )


def test_periodic_and_start_state() -> None:
    f = random_series(3)
    s0 = start_state(f)
    s1 = f.state_at(f.duration_s)
    for a, b in zip(s0, s1, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)
    # At t = 0: qd = sum a, qdd = w * sum l b.
    w = f.omega * np.arange(1, f.harmonics + 1)
    np.testing.assert_allclose(s0[1], f.a.sum(axis=1), atol=1e-12)
    np.testing.assert_allclose(s0[2], (f.b * w).sum(axis=1), atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), h=st.integers(1, 6))
def test_analytic_bounds_hold_and_single_harmonic_is_tight(seed: int, h: int) -> None:
    f = random_series(seed, n=2, h=h, f=0.1)
    t = np.linspace(0.0, f.period_s, 4001)
    bounds = derivative_bounds(f)
    for k in range(4):
        x = basis(t, f.omega, f.harmonics, k) @ f.coefficients().T
        if k == 0:
            x = x - f.q0
        assert np.all(np.abs(x).max(axis=0) <= bounds[k] * (1 + 1e-12) + 1e-12)
    one = FourierTrajectory(0.1, np.zeros(1), np.array([[0.3]]), np.array([[0.4]]))
    t = np.linspace(0.0, 10.0, 100_001)
    _, qd, _, _ = one.evaluate(t)
    assert np.abs(qd).max() == pytest.approx(derivative_bounds(one)[1][0], rel=1e-8)


def test_usage_bounds_a_dense_sampling() -> None:
    robot = load_robot(resource_path("tx40.toml"))
    lim = ExcitationLimits.from_robot(robot)
    rng = np.random.default_rng(5)
    f = FourierTrajectory(
        0.1, lim.middle, rng.normal(size=(6, 5)) * 0.3, rng.normal(size=(6, 5)) * 0.3
    )
    usage = fourier_usage(f, lim, dt=0.05).usage  # coarse grid, rigorous bound
    t = np.linspace(0.0, f.period_s, 200_001)
    q, qd, qdd, qddd = f.evaluate(t)
    dense = np.stack(
        [
            np.maximum(
                (q.max(axis=0) - f.q0) / (lim.upper - f.q0),
                (f.q0 - q.min(axis=0)) / (f.q0 - lim.lower),
            ),
            np.abs(qd).max(axis=0) / lim.velocity,
            np.abs(qdd).max(axis=0) / lim.acceleration,
            np.abs(qddd).max(axis=0) / lim.jerk,
        ]
    )
    assert np.all(usage >= dense - 1e-12)
    # and it is not uselessly loose on a 50 ms grid
    assert np.all(usage <= dense * 1.05 + 1e-9)


def test_scaling_is_linear_about_q0() -> None:
    robot = load_robot(resource_path("tx40.toml"))
    lim = ExcitationLimits.from_robot(robot)
    f = random_series(7, n=6, h=5, f=0.1)
    f = FourierTrajectory(0.1, lim.middle, f.a, f.b)
    u = fourier_usage(f, lim).usage
    np.testing.assert_allclose(fourier_usage(f.scaled(0.5), lim).usage, 0.5 * u, rtol=1e-9)


def test_rejects_inconsistent_shapes() -> None:
    with pytest.raises(TrajectoryError, match="inconsistent shapes"):
        FourierTrajectory(0.1, np.zeros(2), np.zeros((2, 3)), np.zeros((2, 4)))
    with pytest.raises(TrajectoryError, match="base frequency"):
        FourierTrajectory(0.0, np.zeros(1), np.zeros((1, 1)), np.zeros((1, 1)))
