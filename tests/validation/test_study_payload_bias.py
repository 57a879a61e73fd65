"""benchmarks/study_payload_bias.py at small size: its ``cell`` seeds are the validation
study's own draws, and each variant removes what it names and nothing else."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from drivegain.dynamics.params import truth_vector
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
    for row in ("cell: b mean", "cell: c std", "cell: gains mean, j1-j6"):
        assert row in text
    assert [(o[0], o[1]) for o in out] == [("cell", 0), ("cell", 1)]
    world = make_world()
    scenario = next(s for s in SCENARIOS if s.key == KEY)
    seed = run_seed(world, 1, scenario, tuple(m for m in METHODS if m.key == OURS))
    zb = payload_z([seed], OURS, world.payload.values, "b")[0]
    zb[world.payload.known_mask()] = np.nan
    np.testing.assert_allclose(out[1][2], zb, rtol=1e-9, equal_nan=True)
    # payload b's mass is known (it scales the gains): no z; payload c has all ten
    assert np.isnan(out[1][2][world.payload.known_mask()]).all()
    assert np.isfinite(out[1][3]).all()
    zg = (seed.gains[OURS] - world.truth.gains) / seed.std[OURS]
    np.testing.assert_allclose(out[1][4], zg, rtol=1e-9)


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
