"""Entries near reversals of Coulomb friction (identify/reversals.py) and their weight in the ML.

Checked against independent derivations: which currents a friction torque reaches from the
principle of virtual work on the transmission (u = K⁻ᵀ τ), the share of a sine's period near
its reversals from arcsin, and the whitening against a per-sample loop.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from drivegain.config import resource_path
from drivegain.config.robot import load_robot
from drivegain.errors import UsageError
from drivegain.identify.design import Design, make_design
from drivegain.identify.ml import _kappa, ml_fit
from drivegain.identify.mlmodel import Whitening, run_arrays, run_pair
from drivegain.identify.reversals import (
    coulomb_sources,
    reversal_entries,
    reversal_marks,
    source_names,
)

TX40 = load_robot(resource_path("tx40.toml"))


def test_friction_reaches_the_currents_of_the_motors_it_acts_on() -> None:
    velocity, reach = coulomb_sources(TX40)
    k = TX40.transmission()
    n = TX40.n
    # the joints' own velocities, then motor 6 of the coupled wrist (q_m6 ∝ q5 + q6)
    assert velocity.shape == (n + 1, n)
    np.testing.assert_array_equal(velocity[:n], np.eye(n))
    np.testing.assert_allclose(velocity[n], k[5] / k[5, 5])
    # Virtual work: joint torques τ = Kᵀ u from motor torques u, so u = K⁻ᵀ τ. A joint's
    # friction is a joint torque e_j; motor 6's own friction is a motor torque e_6.
    k_inv_t = np.linalg.inv(k.T)
    expected = [np.abs(k_inv_t @ np.eye(n)[j]) > 1e-12 for j in range(n)]
    expected.append(np.eye(n)[5] > 0)
    np.testing.assert_array_equal(reach, np.array(expected))
    # in words: joint 6's friction reaches drives 5 and 6, motor 6's only drive 6
    assert reach[5].tolist() == [False] * 4 + [True, True]
    assert reach[6].tolist() == [False] * 5 + [True]


def test_zones_sit_at_the_reversals_for_the_share_arcsin_gives() -> None:
    t = np.arange(0, 20.0, 1e-3)
    qd = np.ones((t.size, TX40.n))
    qd[:, 0] = np.sin(2 * np.pi * 0.5 * t)  # joint 1 reverses every second
    qd[:, 4] = 1.0 + 0.5 * np.sin(2 * np.pi * 0.2 * t)  # joint 5 never reverses...
    qd[:, 5] = -qd[:, 4] + 0.3 * np.sin(2 * np.pi * 0.3 * t)  # ...but motor 6 (q5 + q6) does
    zones = reversal_marks(qd, TX40, fraction=0.1)[0]
    # |sin| ≤ 0.1 · RMS = 0.1/√2 for 2/π · arcsin(0.1/√2) of the time
    share = 2 / math.pi * math.asin(0.1 / math.sqrt(2))
    assert zones[:, 0].mean() == pytest.approx(share, rel=0.02)
    assert np.all(np.abs(qd[zones[:, 0] > 0, 0]) <= 0.1 / math.sqrt(2) + 1e-12)
    # joints 2-5 and their drives never reverse; motor 6 reaches drive 6 only
    assert not zones[:, 1:5].any()
    motor6 = np.abs(qd[:, 4] + qd[:, 5])
    rms6 = math.sqrt(float(np.mean(motor6**2)))
    np.testing.assert_array_equal(zones[:, 5] > 0, motor6 <= 0.1 * rms6)


def test_reversal_signs_are_the_velocity_s_sign_inside_its_zone_only() -> None:
    t = np.arange(0, 20.0, 1e-3)
    qd = np.ones((t.size, TX40.n))
    qd[:, 0] = np.sin(2 * np.pi * 0.5 * t)  # reverses every second
    qd[:, 1] = 0.0  # at rest all along: its zone is the whole run, no column of its own
    qd[:, 4] = 1.0 + 0.5 * np.sin(2 * np.pi * 0.2 * t)  # joint 5 never reverses...
    qd[:, 5] = -qd[:, 4] + 0.3 * np.sin(2 * np.pi * 0.3 * t)  # ...but motor 6 (q5 + q6) does
    signs = reversal_marks(qd, TX40, fraction=0.1)[1]
    assert signs.shape == (t.size, TX40.n + 1)
    near1 = np.abs(qd[:, 0]) <= 0.1 / math.sqrt(2)  # 0.1 RMS of a unit sine
    np.testing.assert_array_equal(signs[:, 0], np.where(near1, np.sign(qd[:, 0]), 0.0))
    assert near1.mean() == pytest.approx(2 / math.pi * math.asin(0.1 / math.sqrt(2)), rel=0.02)
    assert not signs[:, 1:6].any()
    motor6 = qd[:, 4] + qd[:, 5]
    near6 = np.abs(motor6) <= 0.1 * math.sqrt(float(np.mean(motor6**2)))
    np.testing.assert_array_equal(signs[:, 6], np.where(near6, np.sign(motor6), 0.0))


def test_reversal_columns_enter_the_joints_their_velocity_moves() -> None:
    joint, source, weight = reversal_entries(TX40)
    velocity = coulomb_sources(TX40)[0]
    rebuilt = np.zeros_like(velocity)
    rebuilt[source, joint] = weight
    np.testing.assert_array_equal(rebuilt, velocity)
    # the joints' own on their joint; motor 6's on joints 5 and 6, as its velocity q5 + q6
    assert sorted(joint[source == 6].tolist()) == [4, 5]
    assert source_names(TX40) == [*TX40.joint_names, "motor j5+j6"]


def _exact_pair(world, noisy_run, seed: int) -> tuple[Design, Design]:
    """Designs of an unloaded and a loaded 20 s run by exact tracking (no sticking).

    The Coulomb columns take the sign of the position cut-off's velocity (10 Hz): with this
    coarse joint quantum (1e-3°) a higher one (the default's 4 × here, after the encoder rule
    of identify/coulombsign.py halved 8 ×) flickers near reversals, where a
    joint crosses an encoder step only every few samples, which is an excess there of its own
    (docs/model.md, "Where the Coulomb sign comes from").
    """
    rng = np.random.default_rng(seed)
    bp = world.bases[world.robot.wrist_friction]
    cut = 10.0  # the position cut-off: ten times the runs' highest harmonic (1 Hz)
    runs = [
        noisy_run(0, None, rng, duration=20.0, label="unloaded", sign_cutoff_hz=cut),
        noisy_run(1, world.payload, rng, duration=20.0, label="loaded", sign_cutoff_hz=cut),
    ]
    a, b = (make_design(r, bp, world.robot.wrist_friction, world.robot) for r in runs)
    return a, b


def test_without_sticking_the_reversal_coulomb_terms_are_nought(world, noisy_run) -> None:
    """Exact tracking: the friction is Fc·sign(v) at reversals too, so each coefficient is
    zero within its σ, and the gains move by a fraction of σ with them."""
    a, b = _exact_pair(world, noisy_run, 29)
    assert all(d.run.reversal_coulomb is not None and d.run.reversal_coulomb.size for d in (a, b))
    fit = ml_fit(a, b, world.payload, runs=run_pair(a, b, world.payload))
    none = np.empty(0, dtype=np.intp)
    without = ml_fit(
        a, b, world.payload, runs=[run_arrays(d, world.payload, True, none) for d in (a, b)]
    )
    assert fit.coulomb.size == a.run.reversal_coulomb.size and without.coulomb.size == 0
    assert np.all(np.abs(fit.coulomb) < 4.0 * fit.coulomb_std), fit.coulomb / fit.coulomb_std
    assert np.all(np.abs(fit.gains - without.gains) < 0.3 * without.gain_std)
    assert fit.chi.size == without.chi.size == a.nb
    # one run with the columns, one without: refused rather than misread
    mixed = [run_arrays(a, world.payload), run_arrays(b, world.payload, True, none)]
    with pytest.raises(UsageError, match="run_pair"):
        ml_fit(a, b, world.payload, runs=mixed)
    # the marginal covariance of (χ, g, χ_uL) is the full one without c's rows and columns
    cov = fit.marginal_covariance
    assert cov.shape == without.covariance.shape
    np.testing.assert_array_equal(np.sqrt(np.diag(cov))[a.nb : a.nb + a.n], fit.gain_std)


def test_whitening_scales_each_entry_by_its_share_then_whitens() -> None:
    rng = np.random.default_rng(3)
    n, samples = 4, 50
    a = rng.standard_normal((n, n))
    noise = a @ a.T + n * np.eye(n)
    kappa = 20 * rng.random(n)
    share = np.where(rng.random((samples, n)) < 0.5, 0.0, rng.random((samples, n)))
    w = Whitening(noise, kappa)
    x = rng.standard_normal((samples, n))
    jac = rng.standard_normal((samples, n, 7))
    l_inv = np.linalg.inv(np.linalg.cholesky(noise))
    for k in range(samples):
        s_inv = np.diag(1 / np.sqrt(1 + kappa * share[k]))
        np.testing.assert_allclose(w.apply(x, share)[k], l_inv @ s_inv @ x[k], rtol=1e-12)
        np.testing.assert_allclose(w.apply(jac, share)[k], l_inv @ s_inv @ jac[k], rtol=1e-12)
    # no shares, or κ = 0: the plain whitening
    np.testing.assert_allclose(w.apply(x, None), x @ l_inv.T, rtol=1e-12)
    np.testing.assert_allclose(Whitening(noise, np.zeros(n)).apply(x, share), x @ l_inv.T)


def test_kappa_is_the_likelihood_s_for_variance_growing_with_the_share() -> None:
    """Residuals drawn with variance 1 + κ s: the estimate finds κ; without excess, 0."""
    rng = np.random.default_rng(5)
    share = rng.random((20000, 1)) ** 3
    runs = [SimpleNamespace(reversal=share)]
    for kappa in (0.0, 3.0, 40.0):
        e = rng.standard_normal(share.shape) * np.sqrt(1 + kappa * share)
        found = _kappa([e], runs, 0, 1.0, 1e-16)  # type: ignore[list-item]
        assert found == pytest.approx(kappa, abs=0.05 + 0.1 * kappa)
        # a second run without shares (all its entries ordinary) changes nothing
        two = [*runs, SimpleNamespace(reversal=None)]
        plain = rng.standard_normal((100, 1))
        assert _kappa([e, plain], two, 0, 1.0, 1e-16) == found  # type: ignore[list-item]
    assert _kappa([e], [SimpleNamespace(reversal=None)], 0, 1.0, 1e-16) == 0.0  # type: ignore[list-item]


def test_without_excess_near_reversals_the_fit_is_the_plain_one(world, noisy_run) -> None:
    """Exact tracking (no sticking): κ stays small and the gains move by a fraction of σ."""
    a, b = _exact_pair(world, noisy_run, 23)
    assert all((d.run.reversal_share > 0.02).any() for d in (a, b))
    fit = ml_fit(a, b, world.payload)
    plain = ml_fit(a, b, world.payload, runs=[run_arrays(d, world.payload, False) for d in (a, b)])
    assert np.all(plain.kappa == 0.0)
    assert fit.kappa.max() < 1.0  # an entry wholly near reversals: less than twice the variance
    assert np.all(np.abs(fit.gains - plain.gains) < 0.3 * plain.gain_std)
