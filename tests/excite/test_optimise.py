"""The optimiser on a small problem: improves on its random start, stays rigorously feasible,
and is reproducible whatever the number of workers."""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.config import load_robot, resource_path
from drivegain.dynamics.model import build_model
from drivegain.dynamics.regressor import stack_joint_major, standard_regressor
from drivegain.errors import InputError
from drivegain.excite.criteria import Criterion, design_model
from drivegain.excite.limits import ExcitationLimits, fourier_usage
from drivegain.excite.optimise import (
    CRITERION_SAMPLES,
    MAX_ITER,
    NOMINAL_START_S,
    ExcitationSettings,
    optimise,
    plan_budget,
)


@pytest.fixture(scope="module")
def robot():
    return load_robot(resource_path("tx40.toml"))


def test_budget_maps_deterministically() -> None:
    assert plan_budget(NOMINAL_START_S * 10) == (10, MAX_ITER)
    assert plan_budget(NOMINAL_START_S * 10.9) == (10, MAX_ITER)
    starts, iters = plan_budget(NOMINAL_START_S / 3)
    assert starts == 1 and 10 <= iters < MAX_ITER
    with pytest.raises(InputError):
        plan_budget(0.0)


def test_small_optimisation_improves_and_is_feasible(robot) -> None:
    settings = ExcitationSettings(harmonics=2, starts=2, max_iter=25, seed=3, jobs=2)
    seen = []
    result = optimise(robot, settings, lambda r, best: seen.append((r.index, best.index)))
    assert sorted(i for i, _ in seen) == [0, 1]
    assert [s.index for s in result.starts] == [0, 1]
    best = min(result.starts, key=lambda s: s.objective)
    for s in result.starts:
        assert s.cond < s.initial_cond  # SLSQP improved on its random feasible start
        print(f"start {s.index}: random {s.initial_cond:.3g} -> {s.cond:.3g} ({s.message})")
    assert result.objective == best.objective
    lim = ExcitationLimits.from_robot(robot)
    assert fourier_usage(result.fourier, lim).worst <= 1.0
    # Independent dense check of the excitation against the working limits.
    t = np.linspace(0.0, result.fourier.period_s, 20_001)
    q, qd, qdd, qddd = result.fourier.evaluate(t)
    assert np.all(q <= lim.upper + 1e-12) and np.all(q >= lim.lower - 1e-12)
    assert np.all(np.abs(qd) <= lim.velocity) and np.all(np.abs(qdd) <= lim.acceleration)
    assert np.all(np.abs(qddd) <= lim.jerk)
    # Same seed, one worker: the same trajectory, to the bit.
    again = optimise(robot, ExcitationSettings(harmonics=2, starts=2, max_iter=25, seed=3, jobs=1))
    np.testing.assert_array_equal(again.fourier.coefficients(), result.fourier.coefficients())


def test_logdet_criterion_improves_the_information(robot) -> None:
    settings = ExcitationSettings(
        harmonics=2, starts=1, max_iter=15, seed=1, criterion=Criterion.LOGDET
    )
    result = optimise(robot, settings)
    start = result.starts[0]
    assert start.objective < start.initial_objective
    # the criterion is -log det(AᵀA)/p: recompute it independently on the optimiser's grid
    model = build_model(robot)
    t = np.arange(CRITERION_SAMPLES) * result.fourier.period_s / CRITERION_SAMPLES
    w = standard_regressor(model, *result.fourier.evaluate(t)[:3])
    a = stack_joint_major(w)[:, design_model(model).kept]
    sign, logdet = np.linalg.slogdet(a.T @ a)
    assert sign > 0
    assert start.objective == pytest.approx(-logdet / a.shape[1], rel=1e-9)


def test_the_model_built_beside_the_workers_gives_the_same_metrics(robot) -> None:
    """The metrics reuse the criteria's model the driver built while the workers ran (issue
    19): it must be the one a fresh build gives, so the metrics are unchanged to the bit."""
    from drivegain.excite.evaluate import evaluate_metrics

    settings = ExcitationSettings(harmonics=2, starts=1, max_iter=5, seed=2, jobs=1)
    result = optimise(robot, settings)
    assert result.design is not None
    fresh = design_model(build_model(robot))
    np.testing.assert_array_equal(result.design.kept, fresh.kept)
    np.testing.assert_array_equal(result.design.sign_columns, fresh.sign_columns)
    reused = evaluate_metrics(robot, result.fourier, design=result.design, samples=200)
    again = evaluate_metrics(robot, result.fourier, samples=200)
    assert reused == again
