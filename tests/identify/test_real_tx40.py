"""The real Stäubli TX-40 recording (FIGAROH's data, ../shared/data/tx40-real).

Converted to our log format with ``convert csv`` (motor-side positions and torques), then
identified with gains = gear ratios (Case 1: one unloaded run, no payload). FIGAROH's published
values are printed beside ours as a comparison, not a truth (see the data README).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivegain.config import resource_path
from drivegain.config.robot import WristFriction
from drivegain.identify.convert import convert_csv
from drivegain.identify.pipeline import IdentifyRequest, run_identify

ROBOT = resource_path("tx40.toml")


@pytest.fixture(scope="module")
def real_log(tx40_real: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("tx40") / "tx40-real.mcap"
    return convert_csv(
        tx40_real / "pos_read_data.csv",
        tx40_real / "curr_data.csv",
        5000.0,
        ROBOT,
        motor_side=True,
        torque=True,
        out=out,
    )


def test_real_tx40_case1(real_log: Path, tx40_real: Path, tmp_path: Path) -> None:
    outcome = run_identify(
        IdentifyRequest(
            robot=ROBOT,
            unloaded=real_log,
            out=tmp_path / "report",
            gains="gear-ratios",
            reference=tx40_real / "figaroh_TX40_bp_5.csv",
            progress=False,
        )
    )
    res, doc = outcome.result, outcome.report
    fin = res.final
    names = outcome.robot.joint_names
    np.testing.assert_array_equal(res.gains, [32, 32, 45, -48, 45, 32])
    print(
        f"\nreal TX-40, Case 1 (gains = gear ratios), {doc['method']['samples']} samples kept, "
        f"filter {doc['runs'][0]['filter']}"
    )
    print(
        "R² per joint:        "
        + "  ".join(f"{n} {v:.3f}" for n, v in zip(names, fin.r2, strict=True))
    )
    print(f"relative residual norm {fin.relative_error:.4f}")
    cv = res.cv
    print(
        f"held-out last {cv.fraction:.0%}: relative residual norm {cv.relative_error:.4f} "
        f"(fitted part {cv.train_relative_error:.4f}); R² "
        + "  ".join(f"{n} {v:.3f}" for n, v in zip(names, cv.r2, strict=True))
    )
    flagged = [c for c in res.checks if not c.ok]
    print(
        f"friction and rotor inertias: {len(res.checks)} checked, "
        + (", ".join(f"{c.name} flagged ({c.note})" for c in flagged) or "all positive")
    )
    print("ours vs FIGAROH (WLS, published):")
    for row in doc["reference"]["parameters"]:
        if row["name"].startswith(("Fv", "Fc", "Ia", "fvm", "fcm", "ZZ1R")):
            print(
                f"  {row['name']:<5} ours {row['ours']:8.4f} ± {2 * row['std']:.3f} (2σ)   "
                f"FIGAROH {row['published']:8.4f} (%σ {row['published_rel_std_percent']})   "
                f"{row['difference_percent']:+6.1f} %"
            )
    for form, ff in res.forms.items():
        print(
            f"friction form {form.value:<8}: relative {ff.case.relative_error:.6f}, held-out "
            f"{ff.cv.relative_error:.6f}, R² j5 {ff.case.r2[4]:.4f} j6 {ff.case.r2[5]:.4f}"
        )
    margin = res.form_margin()
    assert margin is not None
    print(
        f"better on held-out data: {res.better_form().value} by {100 * margin:.3g} % "  # type: ignore[union-attr]
        + ("(meaningful)" if margin >= 0.01 else "(not meaningful: the forms fit alike)")
    )

    assert np.all(fin.r2 >= 0.95)
    assert fin.relative_error <= 0.13
    assert 0.0 < cv.relative_error < 1.0
    # Every friction coefficient and rotor inertia identified on its own is positive, or
    # flagged in the report's warnings.
    assert {c.name for c in res.checks} >= {"Fv1", "Fc1", "Ia3", "fvm6", "fcm6"}
    for c in flagged:
        assert any(c.name in w for w in res.warnings)
    # Friction and rotor-inertia parameters of FIGAROH matched ours by expression.
    matched = {row["name"] for row in doc["reference"]["parameters"]}
    assert {"Fv1", "Fc1", "Fv6", "fvm6", "fcm6", "Ia3"} <= matched
    assert set(res.forms) == set(WristFriction)
    report = (tmp_path / "report" / "report.md").read_text()
    assert "Published values" in report and "Coupled-wrist friction forms" in report
