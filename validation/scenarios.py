"""The fixed choices of the validation study: noise scenarios, seeds, budget, sample rate.

Every random stream of the study derives from :data:`ROOT_SEED`: seed ``s`` of the scenario at
position ``k`` of :data:`SCENARIOS` draws from ``numpy.random.default_rng((ROOT_SEED, k, s))``
(:func:`scenario_rng`), so a scenario's numbers do not depend on which others run beside it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivegain.errors import InputError


@dataclass(frozen=True)
class Scenario:
    """A noise level of the Monte Carlo.

    Attributes
    ----------
    key
        Short name, used as the key of the results.
    label
        Human-readable description for the document and figures.
    torque_noise
        White joint-torque noise, N·m, entering through the current references with the true
        gains.
    current_fraction
        White noise on each drive's current reference as a fraction of its rated current
        (unequal torque noise per joint), dimensionless.
    """

    key: str
    label: str
    torque_noise: float
    current_fraction: float


SCENARIOS = (
    Scenario("torque-0.05", "torque noise 0.05 N·m", 0.05, 0.0),
    Scenario("torque-0.1", "torque noise 0.1 N·m", 0.1, 0.0),
    Scenario("current-1pct", "current noise 1 % of rated current", 0.0, 0.01),
)
#: Root of every random stream of the study (seed s of noise level k uses (ROOT_SEED, k, s)).
ROOT_SEED = 20120701
#: Encoder quantum at the joint, rad (1e-3°).
QUANTUM = float(np.deg2rad(1e-3))
#: Sample rate of the simulated recordings, Hz (the acquisition default).
RATE_HZ = 250.0
#: Noise seeds per scenario of the full study and of ``--quick``.
DEFAULT_SEEDS = 150
QUICK_SEEDS = 10
#: Wall-clock budget of the whole study, s.
DEFAULT_BUDGET_S = 1500.0
#: Time kept for the tables, the real recording and the document after the Monte Carlo, s.
RESERVE_S = 120.0
#: Target band for the coverage of the reported 2σ intervals (fractions).
COVERAGE_BAND = (0.90, 0.99)


def scenario_level(scenario: Scenario) -> int:
    """Position of ``scenario`` in :data:`SCENARIOS`: the ``k`` of its random streams.

    Raises
    ------
    InputError
        If no scenario of :data:`SCENARIOS` has its key (its seeds would have no stream).
    """
    keys = [s.key for s in SCENARIOS]
    if scenario.key not in keys:
        raise InputError(
            f"unknown scenario {scenario.key!r}; the study knows {', '.join(keys)}",
            key="scenario",
        )
    return keys.index(scenario.key)


def scenario_rng(scenario: Scenario, seed: int) -> np.random.Generator:
    """The random generator of seed ``seed`` (≥ 0) of ``scenario``."""
    return np.random.default_rng((ROOT_SEED, scenario_level(scenario), seed))
