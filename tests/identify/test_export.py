"""``drivegain export urdf``: Pinocchio's inverse dynamics of the exported URDF plus the
controller TOML reproduce the model's torques (an MDH robot with the coupled wrist, both friction
forms, and a URDF robot with a fixed tool)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from drivegain.cli import main
from drivegain.config import load_robot, load_truth, resource_path
from drivegain.config.robot import Robot
from drivegain.dynamics.base import random_states
from drivegain.dynamics.model import build_model
from drivegain.dynamics.params import (
    N_PER_JOINT,
    standard_names,
    to_pinocchio_order,
    truth_vector,
)
from drivegain.identify.export import com_inertia, exported_torque, load_exported
from drivegain.identify.synth import true_torque

ARM4 = Path(__file__).resolve().parents[1] / "data" / "arm4.toml"


def _report(tmp: Path, robot: Robot, chi: np.ndarray, gains: np.ndarray, form: str) -> Path:
    doc = {
        "format_version": 1,
        "consistent": {
            "standard_names": standard_names(robot),
            "standard": [float(v) for v in chi],
            "gains": {"values": [float(g) for g in gains]},
            "friction": form,
        },
    }
    path = tmp / "report.json"
    path.write_text(json.dumps(doc))
    return path


def _export(tmp: Path, robot_path: Path, report: Path) -> tuple[Path, Path]:
    urdf = tmp / "out" / "robot.urdf"
    args = ["export", "urdf", "--report", str(report), "--robot", str(robot_path)]
    assert main([*args, "--out", str(urdf)]) == 0
    return urdf, urdf.with_suffix(".controller.toml")


def test_com_inertia_matches_pinocchio() -> None:
    truth = load_truth(resource_path("sim/tx40-truth.toml"))
    for link in truth.links:
        p10 = np.concatenate([link.inertia, link.first_moment, [link.mass]])
        m, c, i_c = com_inertia(p10)
        ref = pin.Inertia.FromDynamicParameters(to_pinocchio_order(p10))
        assert m == pytest.approx(ref.mass, rel=1e-14)
        np.testing.assert_allclose(c, ref.lever, atol=1e-15)
        np.testing.assert_allclose(i_c, ref.inertia, atol=1e-15)


@pytest.mark.parametrize("form", ["physical", "paper"])
def test_tx40_export_reproduces_model_torques(tmp_path: Path, form: str) -> None:
    robot_path = resource_path("tx40.toml")
    robot = load_robot(robot_path)
    truth = load_truth(resource_path("sim/tx40-truth.toml"))
    chi = truth_vector(robot, truth)
    chi[N_PER_JOINT - 1 :: N_PER_JOINT][: robot.n] = np.linspace(-0.3, 0.4, robot.n)  # offsets
    urdf, ctrl_path = _export(
        tmp_path, robot_path, _report(tmp_path, robot, chi, truth.gains, form)
    )
    model, ctrl = load_exported(urdf, ctrl_path)
    assert model.nq == robot.n
    np.testing.assert_allclose(ctrl.gains, truth.gains)
    q, qd, qdd = random_states(build_model(robot), 50, np.random.default_rng(4))
    ours = true_torque(build_model(robot), chi, q, qd, qdd, form)
    theirs = exported_torque(model, ctrl, q, qd, qdd)
    assert np.linalg.norm(theirs - ours) / np.linalg.norm(ours) < 1e-12
    # MDH frames: the URDF's link masses are the truth's.
    masses = [model.inertias[i].mass for i in range(1, model.njoints)]
    np.testing.assert_allclose(masses, [lk.mass for lk in truth.links], rtol=1e-14)


def test_urdf_robot_export_keeps_its_file(tmp_path: Path) -> None:
    robot = load_robot(ARM4)
    model = build_model(robot)
    rng = np.random.default_rng(8)
    chi = np.zeros(len(standard_names(robot)))
    for j in range(robot.n):
        # Scaled original inertias (the fixed tool merged into link 4) and some friction.
        dyn = np.asarray(model.pin_model.inertias[j + 1].toDynamicParameters())
        m, mx, my, mz, ixx, ixy, iyy, ixz, iyz, izz = 1.3 * dyn
        chi[N_PER_JOINT * j : N_PER_JOINT * (j + 1)] = [
            ixx, ixy, ixz, iyy, iyz, izz, mx, my, mz, m,
            *rng.uniform(0.01, 1.0, 3), 0.1,
        ]  # fmt: skip
    urdf, ctrl_path = _export(
        tmp_path, ARM4, _report(tmp_path, robot, chi, robot.apriori_gains, "physical")
    )
    text = urdf.read_text()
    assert 'name="tool_mount"' in text and 'type="fixed"' in text  # the robot's own file
    pmodel, ctrl = load_exported(urdf, ctrl_path)
    q, qd, qdd = random_states(model, 50, rng)
    ours = true_torque(model, chi, q, qd, qdd)
    theirs = exported_torque(pmodel, ctrl, q, qd, qdd)
    assert np.linalg.norm(theirs - ours) / np.linalg.norm(ours) < 1e-12
