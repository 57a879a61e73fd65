"""Physically consistent identification (identify --consistent) on simulated runs.

Checked against independent computations: eigenvalues of the pseudo-inertia matrix against the
parallel-axis test of :func:`drivegain.config.inertia.physical_violation`, a noise-free
simulation (the consistent fit must then return the truth's base parameters), and held-out data.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from drivegain.cli import build_parser, main
from drivegain.config.inertia import physical_violation
from drivegain.config.robot import WristFriction
from drivegain.dynamics.params import truth_vector, with_payload
from drivegain.identify.cases import fit_case
from drivegain.identify.consistent import (
    cross_validate_consistent,
    fit_consistent,
    pseudo_inertia,
    pseudo_inertia_eigenvalues,
)
from drivegain.identify.crossval import cross_validate
from drivegain.identify.design import make_design

FORM = WristFriction.PHYSICAL


def test_pseudo_inertia_matches_parallel_axis_test() -> None:
    """J ⪰ 0 exactly when the inertia about the COM is a real body's (triangle inequality)."""
    rng = np.random.default_rng(5)
    agree = 0
    for _ in range(400):
        m = rng.uniform(0.1, 5.0)
        c = rng.normal(0.0, 0.2, 3)
        # Random principal moments, some violating the triangle inequality.
        d = rng.uniform(0.0, 1.0, 3) * np.array([1.0, 1.0, rng.uniform(0.5, 3.0)])
        rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        i_c = rot @ np.diag(d) @ rot.T
        i_o = i_c + m * (float(c @ c) * np.eye(3) - np.outer(c, c))
        # [XX XY XZ YY YZ ZZ MX MY MZ M]
        p10 = np.array([*i_o[0], i_o[1, 1], i_o[1, 2], i_o[2, 2], *(m * c), m])
        real = physical_violation(m, m * c, p10[:6]) is None
        eig = pseudo_inertia_eigenvalues(p10)
        assert (eig[0] >= -1e-12) == real
        agree += 1
    assert agree == 400
    # A point mass at c: J = m [c; 1][c; 1]ᵀ (rank one).
    c = np.array([0.1, -0.2, 0.3])
    p10 = np.array([*(np.zeros(6)), *(2.0 * c), 2.0])
    i_o = 2.0 * (float(c @ c) * np.eye(3) - np.outer(c, c))
    p10[:6] = [i_o[0, 0], i_o[0, 1], i_o[0, 2], i_o[1, 1], i_o[1, 2], i_o[2, 2]]
    v = np.append(c, 1.0)
    np.testing.assert_allclose(pseudo_inertia(p10), 2.0 * np.outer(v, v), atol=1e-15)


def _designs(world, a, b):
    bp = world.bases[FORM]
    return bp, [make_design(a, bp, FORM, world.robot), make_design(b, bp, FORM, world.robot)]


def test_short_noisy_run_inconsistent_payload_made_realisable(world, noisy_run) -> None:
    rng = np.random.default_rng(3)
    a = noisy_run(0, None, rng, duration=6.0, torque_noise=2.0, label="unloaded")
    b = noisy_run(1, world.payload, rng, duration=6.0, torque_noise=2.0, label="loaded")
    bp, designs = _designs(world, a, b)
    gains = world.truth.gains
    case = fit_case("given", designs, gains, bp.names)
    # The unconstrained fit's payload is not a real body.
    eig_u = pseudo_inertia_eigenvalues(case.payloads[0].values)
    assert eig_u[0] < 0.0
    prior = truth_vector(world.robot, world.truth)
    fit = fit_consistent(designs, bp, world.robot, gains, case.sigma_joint, prior=prior)
    for c in fit.constraints:
        if c.kind == "pseudo_inertia":
            assert c.value >= -1e-9, c
        else:
            assert c.value >= -1e-9, c
    eig_c = pseudo_inertia_eigenvalues(fit.payloads[0])
    assert eig_c[0] >= -1e-9 * eig_c[-1]
    assert any(c.name.startswith("payload") for c in fit.active)
    # Base combinations of the standard parameters are the reported base parameters.
    np.testing.assert_allclose(bp.regroup(fit.standard), fit.base, rtol=0, atol=1e-12)
    # The constrained fit costs little on the fitted data ...
    assert fit.relative_error <= 1.05 * case.relative_error
    assert fit.objective_ratio >= 1.0 - 1e-6
    # ... and predicts held-out data within 5 % of the unconstrained fit (here: better).
    cv_u = cross_validate(designs, gains, bp.names, 0.3)
    cv_c = cross_validate_consistent(designs, bp, world.robot, gains, 0.3, prior=prior)
    print(
        f"\nshort noisy run: payload λ_min unconstrained {eig_u[0]:.3g}, consistent "
        f"{eig_c[0]:.3g}; relative residual {case.relative_error:.4f} -> "
        f"{fit.relative_error:.4f}; held-out {cv_u.relative_error:.4f} -> "
        f"{cv_c.relative_error:.4f}; active {[c.name for c in fit.active]}"
    )
    assert cv_c.relative_error <= 1.05 * cv_u.relative_error


def test_long_clean_run_both_fits_agree(world, exact_run) -> None:
    a = exact_run(0, None, duration=20.0, label="unloaded")
    b = exact_run(1, world.payload, duration=20.0, label="loaded")
    bp, designs = _designs(world, a, b)
    gains = world.truth.gains
    case = fit_case("given", designs, gains, bp.names)
    chi_true = truth_vector(world.robot, world.truth)
    # Noise-free: the unconstrained fit is the truth's base parameters.
    np.testing.assert_allclose(case.base, bp.regroup(chi_true), rtol=1e-6, atol=1e-8)
    fit = fit_consistent(designs, bp, world.robot, gains, case.sigma_joint, prior=None)
    scale = np.maximum(np.abs(case.base), 1e-3)
    assert np.max(np.abs(fit.base - case.base) / scale) < 1e-4
    np.testing.assert_allclose(fit.payloads[0], world.payload.values, rtol=1e-4, atol=1e-6)
    assert fit.relative_error < 1e-5
    truth_l6 = with_payload(world.robot, chi_true, world.payload)
    assert np.all(np.isfinite(truth_l6))


def test_gain_sign_mode_solves_gains(world, noisy_run) -> None:
    rng = np.random.default_rng(11)
    a = noisy_run(0, None, rng, duration=20.0, label="unloaded")
    b = noisy_run(1, world.payload, rng, duration=20.0, label="loaded")
    bp, designs = _designs(world, a, b)
    case = fit_case("given", designs, world.truth.gains, bp.names)
    fit = fit_consistent(
        designs,
        bp,
        world.robot,
        world.robot.apriori_gains,
        case.sigma_joint,
        prior=truth_vector(world.robot, world.truth),
        gain_mode="apriori-sign",
    )
    assert np.all(np.sign(fit.gains) == np.sign(world.robot.apriori_gains))
    np.testing.assert_allclose(fit.gains, world.truth.gains, rtol=0.03)
    assert [c for c in fit.constraints if c.kind == "gain_sign"]
    # The known payload mass fixes the scale.
    assert fit.payloads[0][9] == pytest.approx(world.payload.mass, rel=1e-6)


def test_command_line_options(tmp_path: Path) -> None:
    args = build_parser().parse_args(
        [
            "identify",
            "--robot",
            "r.toml",
            "--unloaded",
            "a.mcap",
            "--out",
            "o",
            "--consistent",
            "--prior-weight",
            "0.01",
            "--consistent-gains",
            "apriori-sign",
        ]
    )
    assert args.consistent and args.prior_weight == 0.01
    assert args.consistent_gains == "apriori-sign"
    # A report without a consistent section: one line, exit status 2, nothing written.
    report = tmp_path / "report.json"
    report.write_text(json.dumps({"format_version": 1, "gains": []}))
    from drivegain.config import resource_path

    out = tmp_path / "r.urdf"
    code = main(
        [
            "export",
            "urdf",
            "--report",
            str(report),
            "--robot",
            str(resource_path("tx40.toml")),
            "--out",
            str(out),
        ]
    )
    assert code == 2 and not out.exists()
    assert main(["export", "urdf", "--report", str(report), "--robot", "x", "--out", "a.txt"]) == 2
