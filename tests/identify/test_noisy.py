"""Noisy simulated runs at model.md's levels: accuracy and honest standard deviations.

0.05 N·m torque noise and a 1e-3° encoder quantum; velocities and accelerations come from the
quantised positions through the filters, as with real data. Kept small (40 s runs at 250 Hz):
a larger study is in benchmarks/bench_identify.py.
"""

from __future__ import annotations

import numpy as np

from drivegain.dynamics.params import truth_vector
from drivegain.identify.compare import SeedSpread
from drivegain.identify.design import ls_transform, make_design
from drivegain.identify.gains import Estimator
from drivegain.identify.procedure import Options, Problem, run_procedure
from drivegain.identify.weighting import joint_sigma

SEEDS = 20


def test_gains_within_one_percent_and_honest_sigma(world, noisy_run) -> None:
    gains, stds = [], []
    for seed in range(SEEDS):
        rng = np.random.default_rng(1000 + seed)
        a = noisy_run(0, None, rng, label="unloaded")
        b = noisy_run(1, world.payload, rng, label="loaded")
        res = run_procedure(
            Problem(robot=world.robot, bases=world.bases, unloaded=a, loaded=b),
            Options(compare_forms=False),
        )
        assert res.gains_std is not None
        gains.append(res.gains)
        stds.append(res.gains_std)
    spread = SeedSpread.of(gains, stds, world.truth.gains)
    print(
        f"\ngains over {SEEDS} noise seeds: mean %σ "
        f"{100 * np.mean(res.gains_std / np.abs(res.gains)):.3f} %; z over all "
        f"{spread.z.mean():+.2f} ± {spread.z.std():.2f}"
    )
    print("\n".join(spread.describe()))
    assert np.all(np.abs(spread.errors) < 0.01)
    # About 95 %: with 120 correlated draws, 85-100 % is the band an honest σ lands in; the
    # spread of z catches a σ that is right only on average.
    assert 0.85 <= spread.inside.mean() <= 1.0
    assert 0.7 <= spread.z.std() <= 1.3


def test_sigma_iteration_removes_the_a_priori_gain_error(world, noisy_run) -> None:
    """σ_j from OLS with a priori gains carries the gain errors; the WTLS iteration does not.

    The reference is the equation error of the true parameters on the same prepared data
    (torque noise after the decimation filter, plus Coulomb signs of filtered velocities that
    differ from the true ones where a velocity grazes zero): independent of the estimator.
    """
    rng = np.random.default_rng(7)
    a = noisy_run(0, None, rng, label="unloaded")
    b = noisy_run(1, world.payload, rng, label="loaded")
    res = run_procedure(
        Problem(robot=world.robot, bases=world.bases, unloaded=a, loaded=b),
        Options(compare_forms=False, estimator=Estimator.PAPER),
    )
    assert res.wtls is not None and res.wtls.fit is not None and res.wtls.fit.converged
    bp = world.bases[res.friction]
    da = make_design(a, bp, res.friction, world.robot)
    db = make_design(b, bp, res.friction, world.robot)
    chi = bp.regroup(truth_vector(world.robot, world.truth))
    g = world.truth.gains
    err = np.vstack(
        [
            da.torque(g) - da.model_torque(chi, None),
            db.torque(g) - db.model_torque(chi, world.payload.values),
        ]
    )
    expected = np.sqrt(np.mean(err**2, axis=0))
    final = res.wtls.fit.sigma
    assert res.wtls.sigma_initial is not None
    print(
        f"\nσ_j of the true parameters {np.round(expected, 4)} N·m; "
        f"from WTLS {np.round(final, 4)}; "
        f"from OLS with a priori gains {np.round(res.wtls.sigma_initial, 4)}"
    )
    np.testing.assert_allclose(final, expected, rtol=0.1)
    # The a priori gains' errors (up to 24 %) inflate the OLS σ of some joints.
    fa, fb = da.factors(), db.factors()
    ts = [ls_transform(d, s, 1, world.robot.apriori_gains) for d, s in ((da, None), (db, 0))]
    initial = joint_sigma((da, db), (fa, fb), ts)
    np.testing.assert_allclose(initial, res.wtls.sigma_initial)
    assert np.max(initial / expected) > 1.2
