"""benchmarks/study_payload_bias.py at small size: its ``cell`` seeds are the validation
study's own draws, and each variant removes what it names and nothing else."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from drivegain.dynamics.params import truth_vector
from drivegain.identify.leaveout import MISFIT_KAPPA
from drivegain.validation.estimators import METHODS, OURS, run_seed
from drivegain.validation.scenarios import SCENARIOS
from drivegain.validation.statistics import payload_z
from drivegain.validation.world import make_world

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from study_payload_bias import FINE_ENCODER, _world, study

KEY = "random-closed-loop"


def test_the_cell_variant_is_the_study_scenario(capsys: pytest.CaptureFixture[str]) -> None:
    out = study(seeds=2, workers=2, variants=("cell",))
    text = capsys.readouterr().out
    for row in (
        "cell: b mean",
        "cell: c std",
        "cell: left out: b mean",
        "cell: left out / σ̂ all: c std",
        "cell: payload ±2σ coverage",
        "cell: left out: payload ±2σ coverage",
        "cell: Case 2 as identify: b mean",
        "cell: Case 2 as identify: payload ±2σ coverage",
        "cell: gains' κ̂ median per drive",
        "cell: gains mean, j1-j6",
    ):
        assert row in text
    assert [(o.variant, o.seed) for o in out] == [("cell", 0), ("cell", 1)]
    # its own steps give the validation study's seed: the same z of the gains and payloads
    world = make_world()
    scenario = next(s for s in SCENARIOS if s.key == KEY)
    seed = run_seed(world, 1, scenario, tuple(m for m in METHODS if m.key == OURS))
    zb = payload_z([seed], OURS, world.payload.values, "b")[0]
    zb[world.payload.known_mask()] = np.nan
    np.testing.assert_allclose(out[1].b_case2, zb, rtol=1e-9, equal_nan=True)
    zc = payload_z([seed], OURS, world.validation.values, "c")[0]
    np.testing.assert_allclose(out[1].c_case2, zc, rtol=1e-9)
    # the drives stick in this scenario: Case 2 leaves entries out by itself (κ̂ marks them)
    assert (out[1].kappa >= MISFIT_KAPPA).any()
    assert not np.allclose(out[1].c_case2, out[1].c)
    zg = (seed.gains[OURS] - world.truth.gains) / seed.std[OURS]
    np.testing.assert_allclose(out[1].gains, zg, rtol=1e-9)
    # payload b's mass is known (it scales the gains): no z; payload c has all ten
    for z in (out[1].b, out[1].b_left, out[1].b_left_full, out[1].b_case2):
        assert np.isnan(z[world.payload.known_mask()]).all()
    for z in (out[1].c_left, out[1].c_left_full):
        assert np.isfinite(z).all()
    # leaving entries out moves the estimate: another z, over another σ̂
    assert not np.allclose(out[1].c_left, out[1].c)
    assert not np.allclose(out[1].c_left, out[1].c_left_full)


def test_each_variant_removes_what_it_names() -> None:
    cell, smooth, fine = _world("cell"), _world("no-coulomb"), _world("fine-encoder")
    chi_cell = truth_vector(cell.robot, cell.truth)
    chi_smooth = truth_vector(smooth.robot, smooth.truth)
    coulomb = np.zeros(chi_cell.size, dtype=bool)
    coulomb[12 : 14 * cell.robot.n : 14] = True  # Fc of each joint
    coulomb[14 * cell.robot.n + 1 :: 2] = True  # each coupled motor's
    assert np.all(chi_cell[coulomb] != 0.0)
    assert np.all(chi_smooth[coulomb] == 0.0)
    np.testing.assert_array_equal(chi_smooth[~coulomb], chi_cell[~coulomb])
    counts = [j.encoder_counts for j in cell.robot.joints]
    assert [j.encoder_counts for j in fine.robot.joints] == [FINE_ENCODER * c for c in counts]
    np.testing.assert_array_equal(truth_vector(fine.robot, fine.truth), chi_cell)
    np.testing.assert_array_equal(fine.truth.gains, cell.truth.gains)
    with pytest.raises(ValueError, match="unknown variant"):
        _world("no-friction")
    with pytest.raises(ValueError, match="2 seeds"):
        study(seeds=1, workers=1)
