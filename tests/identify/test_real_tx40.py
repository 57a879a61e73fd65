"""The real Stäubli TX-40 recording (FIGAROH's data, ../shared/data/tx40-real).

Converted to our log format with ``convert csv`` (motor-side positions and torques), then
identified with gains = gear ratios (Case 1: one unloaded run, no payload). Skipped, with the
reason, when ../shared is not beside the checkout.

The friction coefficients are judged against the values FIGAROH published for this recording
(data README, WLS column): their %σ are 0.7-3.9 %, and an independent OLS/WLS reproduced them
within 1-7 %, so 15 % leaves room for a different filter and decimation but not for a wrong model
(keeping the samples at rest in pulls the Coulomb coefficients 35-45 % low). The residual bounds
come from the same README: a fit of published quality leaves a relative residual of 0.078, the
known-bad fit (rest samples kept) 0.12.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivegain.config import resource_path
from drivegain.config.robot import WristFriction
from drivegain.identify.pipeline import IdentifyRequest, run_identify

ROBOT = resource_path("tx40.toml")

#: FIGAROH's published WLS friction values on this recording (data README), in our names:
#: fv -> Fv (viscous, N·m·s/rad), fs -> Fc (Coulomb, N·m), fvm6/fsm6 -> fvm6/fcm6 (motor 6 of
#: the coupled wrist, physical columns). Fc6 is not listed: FIGAROH's %σ for it is 30 %.
PUBLISHED_FRICTION = {
    "Fv1": 8.087,
    "Fc1": 7.014,
    "Fv2": 5.594,
    "Fc2": 8.134,
    "Fv3": 1.983,
    "Fc3": 6.283,
    "Fv4": 1.112,
    "Fc4": 2.490,
    "Fv5": 1.854,
    "Fc5": 3.041,
    "Fv6": 0.648,
    "fvm6": 0.616,
    "fcm6": 1.956,
}
#: Largest relative difference to a published friction value.
FRICTION_TOL = 0.15
#: Relative residual norm ‖ρ‖/‖Y‖ of the known-bad fit (rest samples kept in, data README); a
#: fit of published quality leaves 0.078. Both the fit and the held-out prediction must stay
#: below it: a model that only fits its own samples does not.
BAD_FIT_RESIDUAL = 0.12
#: Between the published-quality (0.078) and the known-bad (0.12) residual of the README.
FIT_RESIDUAL = 0.10


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

    # FIGAROH's coupling columns are the physical ones: only that form is comparable.
    assert res.friction is WristFriction.PHYSICAL
    ours = dict(zip(fin.base_names, fin.base, strict=True))
    assert set(PUBLISHED_FRICTION) <= set(ours)
    diff = {k: ours[k] / v - 1.0 for k, v in PUBLISHED_FRICTION.items()}
    print(
        "friction vs published: "
        + "  ".join(f"{k} {ours[k]:.3f} ({100 * d:+.1f} %)" for k, d in diff.items())
    )
    off = {k: f"{100 * d:+.1f} %" for k, d in diff.items() if abs(d) > FRICTION_TOL}
    assert not off, f"friction more than {FRICTION_TOL:.0%} from FIGAROH's published values: {off}"

    assert np.all(fin.r2 >= 0.95)
    assert fin.relative_error <= FIT_RESIDUAL
    # Held out: the last 30 % of the run, predicted by a fit on the rest.
    assert cv.fraction == pytest.approx(0.3)
    assert cv.relative_error <= BAD_FIT_RESIDUAL
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
