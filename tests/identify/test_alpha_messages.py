"""The α search's failures: true messages, reported (issue 16, item 5)."""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.config.robot import WristFriction
from drivegain.errors import IdentificationError
from drivegain.identify.design import make_design
from drivegain.identify.gains import Estimator, identify_gains
from drivegain.identify.procedure import Options, Problem, run_procedure
from drivegain.identify.report import report_json


@pytest.fixture(scope="module")
def designs(world, exact_run):
    bp = world.bases[WristFriction.PHYSICAL]
    a = exact_run(0, None, label="unloaded")
    b = exact_run(1, world.payload, label="loaded")
    return a, b, [make_design(r, bp, WristFriction.PHYSICAL, world.robot) for r in (a, b)]


def test_a_failing_alpha_is_reported_with_its_true_cause(world, designs) -> None:
    _, _, (da, db) = designs
    res = identify_gains(
        da, db, world.payload, world.robot.apriori_gains, alpha_grid=(1e-22, 1e-2, 1e-1, 1.0)
    )
    # Other α solve: the data do see the payload; the failure is the weight's round-off.
    assert np.allclose(res.gains, world.truth.gains, rtol=1e-6)
    assert [a for a, _ in res.failures] == [1e-22]
    # Independent: at α = 1e-22 the unit singular vector's δ is about α·|c|/‖g‖, far below
    # 1e-13 (c the drive weights), which the message quotes.
    assert "|δ|" in res.failures[0][1] and "not seen" not in res.failures[0][1]
    warning = [w for w in res.warnings if "failed at 1 of" in w]
    assert warning and "not because the payload is unseen" in warning[0]


def test_every_alpha_failing_says_both_possible_causes(world, designs) -> None:
    _, _, (da, db) = designs
    with pytest.raises(IdentificationError) as err:
        identify_gains(da, db, world.payload, world.robot.apriori_gains, alpha_grid=(1e-24, 1e-22))
    msg = str(err.value)
    assert "any α tried (1e-24 to 1e-22)" in msg and "too small" in msg


def test_failures_appear_in_report_json(world, designs) -> None:
    a, b, _ = designs
    problem = Problem(robot=world.robot, bases=world.bases, unloaded=a, loaded=b)
    options = Options(
        friction=WristFriction.PHYSICAL,
        estimator=Estimator.PAPER,
        alpha_grid=(1e-22, 1e-2, 1e-1, 1.0),
    )
    result = run_procedure(problem, options)
    doc = report_json(result, world.robot, [], {})
    failures = doc["wtls"]["alpha_failures"]
    assert [f["alpha"] for f in failures] == [1e-22] and "|δ|" in failures[0]["error"]
    assert doc["wtls"]["alpha_curve"][0] == [1e-22, None]
    curve = np.array([e for _, e in doc["wtls"]["alpha_curve"][1:]])
    assert doc["wtls"]["alpha_curve_flatness"] == pytest.approx(
        (curve.max() - curve.min()) / curve.min()
    )
