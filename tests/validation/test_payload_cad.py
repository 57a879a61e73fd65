"""benchmarks/study_payload_cad.py at one seed: the table it prints and the direction of its
numbers (a known value's error goes into the gains with its sign)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from study_payload_cad import study


def test_known_payload_errors_go_into_the_gains(capsys: pytest.CaptureFixture[str]) -> None:
    errors = study(1, "current-1pct", 0.1, 1.0)
    out = capsys.readouterr().out
    names = list(errors)
    assert len(names) == 5 and all(e.shape == (1, 6) for e in errors.values())
    for name in names:
        assert name in out
    exact, high, low = (errors[n][0] for n in names[1:4])
    # The same noise in every row: only the payload file differs. Inertia taken 10 % too large
    # makes every gain larger than with the exact values, 10 % too small every gain smaller.
    assert np.all(high > exact) and np.all(low < exact)
    # ... by far more than the noise moves them between the mass alone and all 10 known.
    assert np.min(high - low) > 2.0 * np.max(np.abs(exact - errors[names[0]][0]))


def test_an_unknown_scenario_is_refused() -> None:
    with pytest.raises(SystemExit, match="--scenario: expected one of"):
        study(1, "torque-7", 0.1, 1.0)
