"""benchmarks/study_misfit.py at small size: its noisy seeds are the validation study's own
draws, and its runs without noise carry the misfit alone (no seed changes them)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from drivegain.validation.estimators import METHODS, OURS, run_seed
from drivegain.validation.scenarios import SCENARIOS
from drivegain.validation.world import make_world

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from study_misfit import _one, study

KEY = "closed-loop"


def test_the_study_splits_closed_loop_sigma(capsys: pytest.CaptureFixture[str]) -> None:
    out = study(seeds=2, trajectories=2, workers=2)
    text = capsys.readouterr().out
    for row in ("no noise: σ̂₀", "sqrt(σ̂² − σ̂₀²)", "seeds' std of the error", "within ±2σ̂₀"):
        assert row in text
    assert [(o[0], o[1], o[2]) for o in out] == [
        (KEY, False, 0),
        (KEY, True, 0),
        (KEY, True, 1),
        ("random-closed-loop", False, 0),
        ("random-closed-loop", False, 1),
    ]
    world = make_world()
    truth = np.abs(np.asarray(world.truth.gains))
    ours = tuple(m for m in METHODS if m.key == OURS)
    scenario = next(s for s in SCENARIOS if s.key == KEY)
    # the noisy seed is the validation study's own seed 0
    seed = run_seed(world, 0, scenario, ours)
    np.testing.assert_allclose(out[1][3] * truth + world.truth.gains, seed.gains[OURS], rtol=1e-12)
    # without the loop's noise the run is the same whatever the seed: the misfit alone, which
    # the noisy run's σ̂ exceeds
    clean = _one((KEY, False, 1))
    np.testing.assert_array_equal(clean[3], out[0][3])
    np.testing.assert_array_equal(clean[4], out[0][4])
    assert np.all(out[1][4] > out[0][4])
    with pytest.raises(ValueError, match="2 seeds"):
        study(seeds=1, trajectories=2, workers=1)
