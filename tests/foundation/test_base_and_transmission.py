"""Base parameters (QR regrouping) and the coupled transmission."""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.config import load_robot, resource_path
from drivegain.config.robot import WristFriction
from drivegain.dynamics.base import base_parameters, random_states
from drivegain.dynamics.model import build_model
from drivegain.dynamics.params import n_standard, standard_names
from drivegain.dynamics.regressor import standard_regressor
from drivegain.dynamics.transmission import (
    current_matrix,
    currents_for_torque,
    joint_to_motor,
    joint_torque,
    motor_to_joint,
    motor_to_joint_torque,
)


@pytest.fixture(scope="module")
def tx40():
    return build_model(load_robot(resource_path("tx40.toml")))


def test_tx40_counts(tx40) -> None:
    assert n_standard(tx40.robot) == 86
    bp = base_parameters(tx40)
    # 54 inertial + friction parameters (Ia6 and both coupling terms included) + 6 offsets.
    assert bp.n_base == 60
    assert sum(not n.startswith("OFF") for n in bp.names) == 54
    assert "MZ2" not in bp.names  # its column is round-off: no effect on any joint
    for name in ("Ia6", "fvm6", "fcm6", "Ia3", "Ia4", "Ia5"):
        assert name in bp.names
    zz1 = next(e for e in bp.expressions if e.startswith("ZZ1R"))
    assert zz1.startswith("ZZ1R = ZZ1 + Ia1 + YY2 + YY3 + 0.07*MZ3 + 0.05185*M3")


@pytest.mark.parametrize("form", list(WristFriction))
def test_base_regressor_reproduces_standard(tx40, form: WristFriction) -> None:
    bp = base_parameters(tx40, seed=3)
    rng = np.random.default_rng(7)
    w = standard_regressor(tx40, *random_states(tx40, 50, rng), wrist_friction=form)
    for _ in range(5):
        chi = rng.normal(size=n_standard(tx40.robot))
        np.testing.assert_allclose(bp.columns(w) @ bp.regroup(chi), w @ chi, rtol=1e-9, atol=1e-9)
    # The regrouping matrix and the regroup function agree.
    chi = rng.normal(size=n_standard(tx40.robot))
    np.testing.assert_allclose(bp.matrix() @ chi, bp.regroup(chi), rtol=1e-12, atol=1e-12)


def test_base_set_does_not_depend_on_samples(tx40) -> None:
    a = base_parameters(tx40, seed=1)
    b = base_parameters(tx40, seed=2, samples=500)
    assert a.names == b.names
    np.testing.assert_allclose(a.beta, b.beta, atol=1e-8)


def test_names_are_the_standard_ones(tx40) -> None:
    names = standard_names(tx40.robot)
    assert names[:14] == [
        "XX1", "XY1", "XZ1", "YY1", "YZ1", "ZZ1", "MX1", "MY1", "MZ1", "M1",
        "Ia1", "Fv1", "Fc1", "OFF1",
    ]  # fmt: skip
    assert names[-2:] == ["fvm6", "fcm6"]


def test_motor_joint_round_trip(tx40) -> None:
    robot = tx40.robot
    rng = np.random.default_rng(0)
    q = rng.uniform(-3, 3, size=(100, 6))
    qm = joint_to_motor(robot, q)
    # Motor 6 turns with K6 (q5 + q6), joint 4 has a negative ratio.
    np.testing.assert_allclose(qm[:, 5], 32.0 * (q[:, 4] + q[:, 5]))
    np.testing.assert_allclose(qm[:, 3], -48.0 * q[:, 3])
    np.testing.assert_allclose(motor_to_joint(robot, qm), q, rtol=0, atol=1e-12)


def test_coupled_current_matrix_matches_power_conservation(tx40) -> None:
    robot = tx40.robot
    rng = np.random.default_rng(1)
    v = rng.normal(size=(20, 6))
    g = np.array([33.7, 32.2, 24.1, -8.80, 16.50, 6.82])
    # Motor torque of drive j = (g_j / N_j) v_j; joint torques = K^T tau_m.
    tau_m = v * (g / robot.gear_ratios)
    expected = motor_to_joint_torque(robot, tau_m)
    np.testing.assert_allclose(joint_torque(robot, v, g), expected, rtol=1e-12)
    vm = current_matrix(robot, v)
    # Eq. (21): the g6 column holds v6 in both the joint-5 and the joint-6 rows.
    np.testing.assert_array_equal(vm[:, 4, 5], v[:, 5])
    np.testing.assert_array_equal(vm[:, 5, 5], v[:, 5])
    assert np.count_nonzero(vm[0]) == 7
    np.testing.assert_allclose(currents_for_torque(robot, expected, g), v, rtol=1e-10)


_FIGAROH_NAMES = {"Izz": "ZZ", "Ixx": "XX", "Iyy": "YY", "Ixy": "XY", "Ixz": "XZ", "Iyz": "YZ",
                  "mx": "MX", "my": "MY", "mz": "MZ", "m": "M", "fv": "Fv", "fs": "Fc",
                  "off": "OFF", "Ia": "Ia", "Iam": "Ia", "fvm": "fvm", "fsm": "fcm"}  # fmt: skip


def _parse_figaroh(expr: str) -> dict[str, float]:
    """``Izz1 + 1.0*Ia1 - 0.05*m3`` -> {"ZZ1": 1, "Ia1": 1, "M3": -0.05}."""
    import re

    terms: dict[str, float] = {}
    for sign, coef, name in re.findall(r"([+-]?)\s*(?:([\d.]+)\*)?([A-Za-z]+\d)", expr):
        base, idx = re.match(r"([A-Za-z]+)(\d)", name).groups()  # type: ignore[union-attr]
        value = float(coef) if coef else 1.0
        terms[_FIGAROH_NAMES[base] + idx] = -value if sign == "-" else value
    return terms


def test_base_set_matches_published_tx40_base_set(tx40, tx40_real) -> None:
    """An independent source: the base parameters published with the real TX-40 recording."""
    import csv

    published = [
        _parse_figaroh(row[0])
        for row in csv.reader((tx40_real / "figaroh_TX40_bp_5.csv").open())
        if row
    ]
    ours = []
    bp = base_parameters(tx40)
    for row, k in enumerate(bp.base_index):
        terms = {bp.standard_names[k]: 1.0}
        for c, d in enumerate(bp.dependent_index):
            if bp.beta[row, c]:
                terms[bp.standard_names[d]] = float(bp.beta[row, c])
        ours.append(terms)
    assert len(ours) == len(published) == 60
    key = lambda t: sorted(t)  # noqa: E731
    for mine, theirs in zip(sorted(ours, key=key), sorted(published, key=key), strict=True):
        assert mine.keys() == theirs.keys()
        for name, value in theirs.items():
            assert mine[name] == pytest.approx(value, abs=5e-6)
