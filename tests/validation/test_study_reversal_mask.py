"""benchmarks/study_reversal_mask.py at small size: the same runs with and without the mask,
its tables printed, its options checked."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from study_reversal_mask import study


def test_the_study_compares_the_mask_on_the_same_runs(capsys: pytest.CaptureFixture[str]) -> None:
    out = study(["closed-loop"], [0.1], seeds=2, workers=2)
    text = capsys.readouterr().out
    for row in ("no mask", "taper 0.1 s", "RMS gain error", "ratio taper 0.1 s / no mask"):
        assert row in text
    assert [(o.taper, o.seed) for o in out] == [(None, 0), (0.1, 0), (None, 1), (0.1, 1)]
    plain, masked = out[0], out[1]
    assert plain.payload_z.size == masked.payload_z.size == 19
    # the mask changed the fit, and σ: it no longer covers the stick
    assert np.all(plain.gain_err != masked.gain_err)
    assert np.all(masked.gain_std < plain.gain_std)


def test_a_longer_excitation_gives_the_same_seeds_more_samples(
    capsys: pytest.CaptureFixture[str],
) -> None:
    short = study(["torque-0.1"], [0.1], seeds=2, workers=1)
    long = study(["torque-0.1"], [0.1], seeds=2, workers=1, periods=3)
    assert "the excitation 3x as long" in capsys.readouterr().out
    # 981 kept samples rather than 231 (the trimmed borders stay the same): σ̂ about
    # √(231/981) = 0.49 of the short runs' (0.38-0.50 measured), where the same runs gave 1
    ratio = np.array([b.gain_std / a.gain_std for a, b in zip(short, long, strict=True)])
    assert np.all((ratio > 0.3) & (ratio < 0.65))


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"seeds": 1}, "2 seeds"),
        ({"scenarios": ["nowhere"]}, "unknown scenario 'nowhere'"),
        ({"tapers": [0.0]}, "taper"),
        ({"periods": 0}, "--periods needs 1 or more"),
        ({"periods": 2, "scenarios": ["random-closed-loop"]}, "shipped excitation only"),
    ],
)
def test_the_study_refuses_bad_options(kw, match) -> None:
    args = {"scenarios": ["closed-loop"], "tapers": [0.1], "seeds": 2, "workers": 1} | kw
    with pytest.raises(ValueError, match=match):
        study(**args)
