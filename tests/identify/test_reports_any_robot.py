"""Reports of a robot without coupled joints and with long joint names (issue 16, item 7)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from drivegain.config.robot import WristFriction
from drivegain.dynamics.model import build_model
from drivegain.identify.columns import bases_for_forms, stored_columns
from drivegain.identify.pipeline import IdentifyOutcome, _summary
from drivegain.identify.procedure import Options, Problem, run_procedure
from drivegain.identify.report import markdown_report, report_json
from drivegain.identify.units import parameter_unit

NAMES = ["shoulder_pan", "shoulder_lift", "elbow_joint", "wrist_1", "wrist_2", "wrist_3_joint"]


@pytest.fixture(scope="module")
def uncoupled(world, simulate_exact):
    """The TX-40 without its coupled wrist, joints renamed: identified from exact runs."""
    joints = tuple(replace(j, name=nm) for j, nm in zip(world.robot.joints, NAMES, strict=True))
    robot = replace(world.robot, couplings=(), joints=joints, name="uncoupled arm")
    model = build_model(robot)
    bases = bases_for_forms(model)
    columns = stored_columns(robot, bases, [6])
    t = np.arange(0.0, 10.0, 1 / 50)
    runs = []
    for which, pay, label in ((0, None, "unloaded"), (1, world.payload, "loaded")):
        q, qd, qdd = world.excitations[which].evaluate(t)[:3]
        runs.append(
            simulate_exact(model, world.truth, columns, t, q, qd, qdd, label=label, payload=pay)
        )
    problem = Problem(robot=robot, bases=bases, unloaded=runs[0], loaded=runs[1])
    result = run_procedure(problem, Options(friction=WristFriction.PHYSICAL))
    doc = report_json(result, robot, [], {})
    return robot, result, doc, markdown_report(doc, result, robot, [], {})


def test_no_coupled_wrist_comparison_without_coupling(world, uncoupled) -> None:
    robot, result, doc, md = uncoupled
    np.testing.assert_allclose(result.gains, world.truth.gains, rtol=1e-6)
    assert len(result.forms) == 1 and doc["friction_forms"]["better"] is None
    assert "friction forms" not in md and "coupled-wrist" not in md.lower()
    summary = _summary(
        IdentifyOutcome(result=result, report=doc, out=Path("out"), files=[], robot=robot),
        robot.joint_names,
    )
    assert "friction form" not in summary


def test_terminal_table_keeps_its_columns_with_long_names(uncoupled) -> None:
    robot, result, doc, _ = uncoupled
    text = _summary(
        IdentifyOutcome(result=result, report=doc, out=Path("out"), files=[], robot=robot),
        robot.joint_names,
    )
    lines = text.splitlines()
    head = next(i for i, ln in enumerate(lines) if ln.startswith("joint"))
    rows = lines[head + 1 : head + 1 + robot.n]
    # Every row: the name, then four numbers, each column ending at the same place.
    ends = {len(r) for r in rows}
    assert len(ends) == 1, rows
    for r, nm, g in zip(rows, NAMES, result.gains, strict=True):
        assert r.startswith(nm + " ")
        assert float(r[len(nm) :].split()[1]) == pytest.approx(g, rel=1e-3)
    assert "(N·m/A)" in lines[head]


def test_units_in_report_tables(uncoupled) -> None:
    md = uncoupled[3]
    assert "a priori g (N·m/A)" in md and "identified g (N·m/A)" in md
    rows = [ln for ln in md.splitlines() if ln.startswith("| Fv1 ") or ln.startswith("| ZZ1R ")]
    assert any("N·m·s/rad" in r for r in rows) and any("kg·m²" in r for r in rows)
    assert "| M_L | kg |" in md


@pytest.mark.parametrize(
    ("name", "unit"),
    [
        ("ZZ1R", "kg·m²"),
        ("XY4", "kg·m²"),
        ("MX2R", "kg·m"),
        ("M3", "kg"),
        ("Ia6", "kg·m²"),
        ("Fv1", "N·m·s/rad"),
        ("Fc2", "N·m"),
        ("OFF3", "N·m"),
        ("fvm6", "N·m·s/rad"),
        ("fcm6", "N·m"),
        ("nonsense", ""),
    ],
)
def test_parameter_units(name: str, unit: str) -> None:
    assert parameter_unit(name) == unit
