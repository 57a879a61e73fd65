"""Consistent identification and URDF export on the real TX-40 recording (../shared/data).

Skipped, with the reason, when ../shared is not beside the checkout (fixture ``tx40_real``).
Gains = gear ratios (Case 1), one unloaded run, as in test_real_tx40.py.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from drivegain.cli import main
from drivegain.config import load_robot, resource_path
from drivegain.config.robot import WristFriction
from drivegain.dynamics.model import build_model
from drivegain.dynamics.params import standard_names
from drivegain.formats.logreader import read_run
from drivegain.identify.columns import bases_for_forms
from drivegain.identify.consistent import pseudo_inertia_eigenvalues
from drivegain.identify.consistent_report import ConsistentRequest
from drivegain.identify.export import exported_torque, load_exported
from drivegain.identify.pipeline import IdentifyRequest, run_identify
from drivegain.identify.prepare import filtered_derivatives
from drivegain.identify.signal import default_filter
from drivegain.identify.synth import true_torque

ROBOT = resource_path("tx40.toml")


@pytest.fixture(scope="module")
def report_dir(real_log: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("tx40c") / "report"
    run_identify(
        IdentifyRequest(
            robot=ROBOT,
            unloaded=real_log,
            out=out,
            gains="gear-ratios",
            progress=False,
            consistent=ConsistentRequest(),
        )
    )
    return out


def test_real_consistent_fit(report_dir: Path) -> None:
    doc = json.loads((report_dir / "report.json").read_text())
    sec = doc["consistent"]
    cv, res = sec["cross_validation"], sec["residual"]
    names = [j["joint"] for j in doc["gains"]]
    print(
        f"\nreal TX-40 consistent fit ({sec['solver']['name']}, solve "
        f"{sec['solver']['solve_time_s']:.3f} s, setup {sec['solver']['setup_time_s']:.3f} s)"
    )
    print(
        f"relative residual: unconstrained {res['unconstrained_relative']:.4f}, consistent "
        f"{res['relative']:.4f}; held-out: unconstrained {cv['unconstrained_relative']:.4f}, "
        f"consistent {cv['relative']:.4f}"
    )
    print(
        "R² unconstrained "
        + " ".join(f"{n} {v:.4f}" for n, v in zip(names, sec["unconstrained_r2"], strict=True))
    )
    print(
        "R² consistent    "
        + " ".join(f"{n} {v:.4f}" for n, v in zip(names, sec["r2"], strict=True))
    )
    print("held-out R² unconstrained " + " ".join(f"{v:.4f}" for v in cv["unconstrained_r2"]))
    print("held-out R² consistent    " + " ".join(f"{v:.4f}" for v in cv["r2"]))
    print(f"active constraints: {sec['active']}")
    robot = load_robot(ROBOT)
    chi = np.array(sec["standard"])
    for j in range(robot.n):
        eig = pseudo_inertia_eigenvalues(chi[14 * j : 14 * j + 10])
        assert eig[0] >= -1e-9 * max(1.0, eig[-1]), f"link {j + 1} not realisable: {eig}"
    for c in sec["constraints"]:
        if c["kind"] == "nonnegative":
            assert c["value"] >= -1e-9, c
    # The base combinations of the standard parameters are the reported consistent ones.
    assert sec["standard_names"] == standard_names(robot)
    bp = bases_for_forms(build_model(robot))[WristFriction(sec["friction"])]
    reported = np.array([b["value"] for b in sec["base_parameters"]])
    np.testing.assert_allclose(bp.regroup(chi), reported, rtol=1e-12, atol=1e-12)
    # Constraints cost little on real data, and the prediction of held-out data does not
    # degrade by more than 5 %.
    assert res["relative"] <= 1.05 * res["unconstrained_relative"]
    assert cv["relative"] <= 1.05 * cv["unconstrained_relative"]
    assert min(sec["r2"]) >= 0.95
    md = (report_dir / "report.md").read_text()
    assert "Physically consistent fit" in md


def test_real_export_urdf_reproduces_torques(
    report_dir: Path, real_log: Path, tmp_path: Path
) -> None:
    urdf = tmp_path / "tx40-identified.urdf"
    code = main(
        [
            "export",
            "urdf",
            "--report",
            str(report_dir / "report.json"),
            "--robot",
            str(ROBOT),
            "--out",
            str(urdf),
        ]
    )
    assert code == 0
    controller = urdf.with_suffix(".controller.toml")
    assert urdf.is_file() and controller.is_file()
    pmodel, ctrl = load_exported(urdf, controller)
    assert pmodel.nq == 6

    # The recorded trajectory, filtered and differentiated as identify does, every 20th sample.
    robot = load_robot(ROBOT)
    log = read_run(real_log, robot.n)
    settings = default_filter(log.rate_hz, None)
    q, qd, qdd = (x[::20] for x in filtered_derivatives(log.position, log.rate_hz, settings))
    sec = json.loads((report_dir / "report.json").read_text())["consistent"]
    chi = np.array(sec["standard"])
    # The identified model: our regressor with the consistent standard parameters (whose base
    # combinations are the identified base parameters).
    model = build_model(robot)
    identified = true_torque(model, chi, q, qd, qdd, sec["friction"])
    exported = exported_torque(pmodel, ctrl, q, qd, qdd)
    rel = np.linalg.norm(exported - identified) / np.linalg.norm(identified)
    print(f"\nexported URDF + controller TOML vs identified model: relative difference {rel:.2e}")
    assert rel < 1e-6
    np.testing.assert_allclose(ctrl.gains, robot.gear_ratios)
