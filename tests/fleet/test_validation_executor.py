"""The validation study's Monte Carlo through an executor gives the serial loop's results."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

from drivegain.validation import estimators


def test_monte_carlo_on_an_executor_matches_the_serial_loop(monkeypatch) -> None:
    def fake_seed(world, seed, scenario):
        return (world, seed, scenario.key)

    monkeypatch.setattr(estimators, "run_seed", fake_seed)
    scenarios = [SimpleNamespace(key="equal"), SimpleNamespace(key="unequal")]
    far = time.perf_counter() + 600
    serial = estimators.monte_carlo("w", 5, far, scenarios, progress=lambda s: None)
    with ThreadPoolExecutor(2) as pool:
        mapped = estimators.monte_carlo(
            "w", 5, far, scenarios, progress=lambda s: None, executor=pool
        )
        assert mapped == serial
        cut = estimators.monte_carlo("w", 5, 0.0, scenarios, lambda s: None, executor=pool)
    assert {k: len(v) for k, v in cut.items()} == {"equal": 1, "unequal": 1}
    assert serial["equal"][3] == ("w", 3, "equal")
