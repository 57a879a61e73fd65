"""``identify --consistent`` and ``export urdf`` end to end on simulated MCAP logs (Case 2:
gains identified by IDIM-WTLS from an unloaded and a loaded run)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.identify.consistent import pseudo_inertia_eigenvalues
from drivegain.identify.export import exported_torque, load_exported
from drivegain.identify.synth import true_torque

ROBOT = resource_path("tx40.toml")
PAYLOAD = resource_path("payloads/calibrated-4590g.toml")


@pytest.fixture(scope="module")
def logs(run_logs, tmp_path_factory) -> dict[str, Path]:
    return run_logs(tmp_path_factory.mktemp("clogs"), {"a": 21, "b": 22}, seconds=20.0)


def _identify(logs: dict[str, Path], out: Path, *extra: str) -> dict:
    args = ["identify", "--robot", str(ROBOT), "--unloaded", str(logs["a"])]
    args += ["--loaded", str(logs["b"]), "--payload", str(PAYLOAD), "--out", str(out)]
    assert main([*args, "--consistent", *extra]) == 0
    return json.loads((out / "report.json").read_text())


def test_identify_consistent_case2_and_export(world, logs, tmp_path: Path) -> None:
    doc = _identify(logs, tmp_path / "rep")
    sec = doc["consistent"]
    assert sec["gains"]["mode"] == "fixed"
    np.testing.assert_allclose(sec["gains"]["values"], [g["value"] for g in doc["gains"]])
    assert sec["solver"]["status"] == "optimal"
    eig = sec["payload"]["pseudo_inertia_eigenvalues"]
    assert eig[0] >= -1e-9 * eig[-1]
    assert sec["payload"]["mass"] == pytest.approx(world.payload.mass, rel=0.02)
    for link in sec["links"]:
        ev = link["pseudo_inertia_eigenvalues"]
        assert ev[0] >= -1e-9 * max(1.0, ev[-1])
    cv = sec["cross_validation"]
    assert cv["relative"] <= 1.05 * cv["unconstrained_relative"]
    assert "Physically consistent fit" in (tmp_path / "rep" / "report.md").read_text()

    urdf = tmp_path / "tx40.urdf"
    ctrl = tmp_path / "tx40-gains.toml"
    args = ["export", "urdf", "--report", str(tmp_path / "rep" / "report.json")]
    args += ["--robot", str(ROBOT), "--out", str(urdf), "--controller", str(ctrl)]
    assert main(args) == 0
    model, controller = load_exported(urdf, ctrl)
    t = np.linspace(0.0, 5.0, 60)
    q, qd, qdd = world.excitations[0].evaluate(t)[:3]
    ours = true_torque(world.model, np.array(sec["standard"]), q, qd, qdd)
    theirs = exported_torque(model, controller, q, qd, qdd)
    assert np.linalg.norm(theirs - ours) / np.linalg.norm(ours) < 1e-9


def test_identify_consistent_gains_with_sign(world, logs, tmp_path: Path) -> None:
    doc = _identify(logs, tmp_path / "rep", "--consistent-gains", "apriori-sign")
    sec = doc["consistent"]
    assert sec["gains"]["mode"] == "apriori-sign"
    g = np.array(sec["gains"]["values"])
    assert np.all(np.sign(g) == np.sign(world.robot.apriori_gains))
    np.testing.assert_allclose(g, world.truth.gains, rtol=0.03)
    assert isinstance(sec["gains"]["active"], list)
    p = sec["payload"]
    p10 = [p[k] for k in ("XX", "XY", "XZ", "YY", "YZ", "ZZ", "MX", "MY", "MZ", "mass")]
    assert pseudo_inertia_eigenvalues(np.array(p10))[0] >= -1e-9
