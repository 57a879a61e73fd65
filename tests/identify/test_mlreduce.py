"""The maximum-likelihood steps on reduced runs equal those built sample by sample (issue 19).

Every quantity :mod:`drivegain.identify.mlreduce` gives (Σ_k ε_k ε_kᵀ, ‖ẽ‖², the R factor of
[J̃ | ẽ]) is checked against the model of :mod:`drivegain.identify.mlmodel` evaluated at every
sample: a coupled wrist (K⁻¹ with an off-diagonal block), a loaded run with known and unknown
payload parameters, entries near reversals with κ ≠ 0, a random noise covariance, and row
blocks that do not divide the run.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from drivegain.errors import UsageError
from drivegain.identify import mlreduce
from drivegain.identify.design import make_design
from drivegain.identify.mlmodel import Whitening, predict, run_arrays, unscaled, whitened_block


@pytest.fixture(scope="module")
def setting(world, noisy_run):
    rng = np.random.default_rng(7)
    bp = world.bases[world.robot.wrist_friction]
    designs = [
        make_design(
            noisy_run(k, pay, rng, duration=8.0, label=f"r{k}"),
            bp,
            world.robot.wrist_friction,
            world.robot,
        )
        for k, pay in ((0, None), (1, world.payload))
    ]
    runs = []
    for d in designs:
        run = run_arrays(d, world.payload)
        n = run.v.shape[1]
        # some entries near reversals, with shares 0-1, so S_k is not the identity
        share = rng.uniform(0.0, 1.0, (run.samples, n)) * (rng.random((run.samples, n)) < 0.3)
        runs.append(replace(run, reversal=share))
    kt_inv = np.linalg.inv(np.asarray(designs[0].kt, float))
    nb, n, nu = runs[0].base_idx.size, runs[0].v.shape[1], runs[1].nu
    theta = np.concatenate(
        [
            rng.standard_normal(nb),
            world.truth.gains * (1 + 0.05 * rng.standard_normal(n)),
            rng.standard_normal(nu),
        ]
    )
    a = rng.standard_normal((n, n))
    whiten = Whitening(a @ a.T + n * np.eye(n), rng.uniform(0.5, 5.0, n))
    return runs, kt_inv, theta, whiten


def test_the_coupled_wrist_is_in_the_setting(setting) -> None:
    _, kt_inv, _, _ = setting
    assert np.count_nonzero(kt_inv - np.diag(np.diag(kt_inv))) > 0


@pytest.mark.parametrize("block", [37, 100_000])
def test_reduced_quantities_equal_the_sample_by_sample_ones(setting, monkeypatch, block) -> None:
    runs, kt_inv, theta, whiten = setting
    monkeypatch.setattr(mlreduce, "BLOCK", block)
    nb = runs[0].base_idx.size
    reduced = [mlreduce.reduce_run(r, kt_inv, whiten.kappa) for r in runs]
    # sample by sample
    blocks = [whitened_block(theta, r, kt_inv, whiten) for r in runs]
    full = np.vstack(
        [
            np.concatenate([jw.reshape(-1, theta.size), ew.reshape(-1, 1)], axis=1)
            for jw, ew in blocks
        ]
    )
    gram = full.T @ full
    eps = np.vstack(
        [unscaled(r.v - predict(theta, r, kt_inv)[0], r.reversal, whiten.kappa) for r in runs]
    )
    # reduced
    r_aug = mlreduce.augmented_factor(reduced, theta, nb, kt_inv, whiten)
    scale = np.abs(gram).max()
    np.testing.assert_allclose(r_aug.T @ r_aug / scale, gram / scale, rtol=0, atol=1e-11)
    np.testing.assert_allclose(
        mlreduce.whitened_sq(mlreduce.residual_gram(reduced, theta, nb, kt_inv), whiten),
        gram[-1, -1],
        rtol=1e-10,
    )
    ref = eps.T @ eps
    np.testing.assert_allclose(
        mlreduce.residual_gram(reduced, theta, nb, kt_inv),
        ref,
        rtol=0,
        atol=1e-10 * np.abs(ref).max(),
    )


def test_without_reversals_the_data_are_not_scaled(setting) -> None:
    runs, kt_inv, _, whiten = setting
    plain = replace(runs[1], reversal=None)
    lay = mlreduce.layout(plain, kt_inv)
    d = mlreduce.data_rows(plain, lay, whiten.kappa, slice(0, 50))
    np.testing.assert_array_equal(d[:, lay.current], plain.v[:50])
    # every column belongs to one drive, each drive's current once
    assert lay.owner.size == lay.size and np.array_equal(
        lay.owner[lay.current], np.arange(lay.current.size)
    )


def test_steps_refuse_runs_reduced_at_another_kappa(setting) -> None:
    runs, kt_inv, theta, whiten = setting
    reduced = [mlreduce.reduce_run(r, kt_inv, np.zeros(whiten.kappa.size)) for r in runs]
    with pytest.raises(UsageError, match="another κ"):
        mlreduce.augmented_factor(reduced, theta, runs[0].base_idx.size, kt_inv, whiten)


def test_a_zero_gain_is_refused(setting) -> None:
    runs, kt_inv, theta, _ = setting
    nb = runs[0].base_idx.size
    bad = theta.copy()
    bad[nb] = 0.0
    lay = mlreduce.layout(runs[0], kt_inv)
    with pytest.raises(UsageError, match="gain is zero"):
        mlreduce.coefficients(lay, bad, nb, kt_inv.shape[0], kt_inv)
