"""The Coulomb sign's choice fits runs a and b by maximum likelihood; the gains' estimate takes
the kept candidate's fit rather than making the same fit again.

Checked against the estimate that fits for itself: the same report to the last digit, and on
designs, the same gains, covariance, test and error model. And a fit that is not of the runs,
not for this estimator or without the test's sums is refused.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.errors import UsageError
from drivegain.identify import prepchoice, procedure
from drivegain.identify.design import make_design
from drivegain.identify.gains import Estimator, estimate_gains
from drivegain.identify.ml import ml_fit

DURATION = 20.0
PAYLOAD = resource_path("payloads/calibrated-4590g.toml")


def _pair(world, noisy_run, seed: int):
    rng = np.random.default_rng(seed)
    bp = world.bases[world.robot.wrist_friction]
    runs = [
        noisy_run(0, None, rng, duration=DURATION, label="unloaded"),
        noisy_run(1, world.payload, rng, duration=DURATION, label="loaded"),
    ]
    return [make_design(r, bp, world.robot.wrist_friction, world.robot) for r in runs]


def test_a_given_fit_gives_the_estimate_of_a_fit_made_there(world, noisy_run) -> None:
    a, b = _pair(world, noisy_run, 11)
    apriori = world.robot.apriori_gains
    own = estimate_gains(a, b, world.payload, apriori)
    fit = ml_fit(a, b, world.payload, influence=True)
    given = estimate_gains(a, b, world.payload, apriori, fit=fit)
    assert given.ml is fit
    np.testing.assert_array_equal(given.gains, own.gains)
    np.testing.assert_array_equal(given.std, own.std)
    np.testing.assert_array_equal(given.covariance, own.covariance)
    assert given.eiv is not None and own.eiv is not None
    assert given.eiv.statistic == own.eiv.statistic and given.eiv.p_value == own.eiv.p_value
    assert given.noise is not None and own.noise is not None
    np.testing.assert_array_equal(given.noise.gain_influence, own.noise.gain_influence)
    np.testing.assert_array_equal(given.noise.gamma, own.noise.gamma)
    assert given.warnings == own.warnings


def test_a_fit_the_estimate_cannot_take_is_refused(world, noisy_run) -> None:
    a, b = _pair(world, noisy_run, 12)
    apriori = world.robot.apriori_gains
    fit = ml_fit(a, b, world.payload, influence=True)
    with pytest.raises(UsageError, match="errors-in-variables"):
        estimate_gains(a, b, world.payload, apriori, fit=replace(fit, influence=None))
    with pytest.raises(UsageError, match="paper's estimator"):
        estimate_gains(a, b, world.payload, apriori, estimator=Estimator.PAPER, fit=fit)
    # a fit of runs with another count of equations, or another model
    with pytest.raises(UsageError, match="other runs"):
        estimate_gains(a, b, world.payload, apriori, fit=replace(fit, rows=fit.rows + a.n))
    with pytest.raises(UsageError, match="other runs"):
        estimate_gains(a, b, world.payload, apriori, fit=replace(fit, chi=fit.chi[1:]))


def test_the_procedure_takes_a_fit_of_its_own_runs_only(world, noisy_run) -> None:
    rng = np.random.default_rng(14)
    u = noisy_run(0, None, rng, duration=DURATION, label="unloaded")
    lo = noisy_run(1, world.payload, rng, duration=DURATION, label="loaded")
    form = world.robot.wrist_friction
    bp = world.bases[form]
    fit = ml_fit(
        make_design(u, bp, form, world.robot),
        make_design(lo, bp, form, world.robot),
        world.payload,
        influence=True,
    )
    problem = procedure.Problem(world.robot, world.bases, u, lo)
    made = procedure.FitMade(form, u, lo, fit)
    assert made.serves(problem, form, Estimator.ML)
    assert not made.serves(problem, form, Estimator.PAPER)
    other = next(f for f in world.bases if f is not form)
    assert not made.serves(problem, other, Estimator.ML)
    # equal runs that are not the problem's own objects: not taken on trust
    assert not made.serves(replace(problem, loaded=replace(lo)), form, Estimator.ML)


def _report(out) -> dict:
    return json.loads((out / "report.json").read_text())


def test_identify_reuses_the_sign_choice_fit_and_reports_the_same(
    run_logs, tmp_path, monkeypatch
) -> None:
    logs = run_logs(tmp_path, {"a": 21, "b": 22}, seconds=30.0)
    args = ["identify", "--robot", "tx40", "--unloaded", str(logs["a"])]
    args += ["--loaded", str(logs["b"]), "--payload", str(PAYLOAD), "--no-plots"]
    given: list[bool] = []
    real = procedure.estimate_gains

    def spy(*a, **kw):
        given.append(kw.get("fit") is not None)
        return real(*a, **kw)

    monkeypatch.setattr(procedure, "estimate_gains", spy)
    assert main([*args, "--out", str(tmp_path / "reused")]) == 0
    reused = _report(tmp_path / "reused")
    notes = [note for run in reused["runs"] for note in run.get("notes", [])]
    # These logs have the choice (the noise rule kept the sign above the position cut-off).
    assert any("chosen by the runs' likelihood" in note for note in notes), notes
    assert given == [True]

    choose = prepchoice.sign_choice

    def without_fit(*a, **kw):
        loaded, _, at_cutoff = choose(*a, **kw)
        return loaded, None, at_cutoff

    monkeypatch.setattr(prepchoice, "sign_choice", without_fit)
    assert main([*args, "--out", str(tmp_path / "fitted")]) == 0
    assert given == [True, False]
    assert _report(tmp_path / "fitted") == reused

    # The paper's estimator makes its own fit: no ML fit is handed to it.
    monkeypatch.setattr(prepchoice, "sign_choice", choose)
    assert main([*args, "--estimator", "paper", "--out", str(tmp_path / "paper")]) == 0
    assert given == [True, False, False]
