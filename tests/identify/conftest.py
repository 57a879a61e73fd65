"""Fixtures of the identify tests: the TX-40, its simulation truth, payloads, excitations,
simulated runs and the MCAP logs made of them."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivegain.config import resource_path
from drivegain.config.payload import Payload
from drivegain.config.robot import WristFriction
from drivegain.formats.fourier import FourierTrajectory
from drivegain.formats.log import RunMetadata
from drivegain.formats.logwriter import write_run
from drivegain.identify.convert import convert_csv
from drivegain.identify.prepare import (
    PreparedRun,
    prepare_recording,
)
from drivegain.identify.signal import default_filter
from drivegain.identify.synth import SyntheticRun, exciting_sum_of_sines, simulate_run
from drivegain.validation.world import Tx40, load_tx40

#: Excitation used by the simulated runs: base frequency and harmonics (bandwidth 1 Hz).
BASE_HZ = 0.2
HARMONICS = 5
#: Noise of model.md: torque noise, N·m, and the encoder quantum at the joint, rad.
TORQUE_NOISE = 0.05
QUANTUM = float(np.deg2rad(1e-3))
#: Sample rate of the simulated MCAP logs, Hz, and the TRAJ.json attached to them (the
#: excitation's base frequency; its coefficients are not read back).
LOG_RATE = 250.0
LOG_TRAJECTORY = {"fourier": {"base_frequency_hz": 0.2, "a": [[0.0] * 5] * 6, "b": [[0.0] * 5] * 6}}


@dataclass(frozen=True)
class World(Tx40):
    """The TX-40 with three separate excitations: runs a, b and the validation run."""

    excitations: tuple[FourierTrajectory, FourierTrajectory, FourierTrajectory]


@pytest.fixture(scope="session", autouse=True)
def _single_blas_thread(single_blas_thread: None) -> None:
    """As the identify command does (see the root conftest)."""


@pytest.fixture(scope="session")
def world() -> World:
    tx40 = load_tx40()
    rng = np.random.default_rng(20120701)
    # Separate trajectories for runs a, b and the validation run, as recorded in practice.
    excitations = tuple(
        exciting_sum_of_sines(
            tx40.model,
            rng,
            base_frequency_hz=BASE_HZ,
            harmonics=HARMONICS,
            candidates=8,
            base=tx40.bases[WristFriction.PHYSICAL],
        )
        for _ in range(3)
    )
    return World(**tx40.parts(), excitations=excitations)  # type: ignore[arg-type]


Simulate = Callable[..., PreparedRun]


def simulate_noisy(
    world: World,
    which: int,
    payload: Payload | None,
    t: np.ndarray,
    rng: np.random.Generator,
    *,
    torque_noise: float | np.ndarray = TORQUE_NOISE,
    current_noise: float | np.ndarray = 0.0,
    quantum: float = QUANTUM,
) -> SyntheticRun:
    """Excitation ``which`` tracked exactly at the times ``t`` (s), with torque noise (N·m),
    current noise and the encoder quantum (rad) drawn from ``rng``."""
    q, qd, qdd = world.excitations[which].evaluate(t)[:3]
    return simulate_run(
        world.model,
        world.truth,
        q,
        qd,
        qdd,
        payload=payload,
        torque_noise=torque_noise,
        current_noise=current_noise,
        quantum=quantum,
        rng=rng,
    )


def write_sim_log(
    world: World,
    path: Path,
    which: int,
    payload: Payload | None,
    seed: int,
    *,
    seconds: float,
    quantum: float = QUANTUM,
    joints: int | None = None,
    trajectory: bool = True,
) -> Path:
    """A simulated run (:func:`simulate_noisy`, seeded with ``seed``) of ``seconds`` at
    :data:`LOG_RATE` written as a drivegain MCAP log at ``path``.

    ``joints`` keeps the first joints only; ``trajectory`` attaches :data:`LOG_TRAJECTORY` as
    ``trajectory.json``.
    """
    t = np.arange(0.0, seconds, 1.0 / LOG_RATE)
    sim = simulate_noisy(world, which, payload, t, np.random.default_rng(seed), quantum=quantum)
    n = world.robot.n if joints is None else joints
    pos, cur = sim.q[:, :n], sim.current_reference[:, :n]
    meta = RunMetadata(
        robot=world.robot.name,
        run="loaded" if payload is not None else "unloaded",
        payload=payload.name if payload is not None else "none",
        joint_names=world.robot.joint_names[:n],
        sync_period_s=1.0 / LOG_RATE,
        started_at="2024-01-01T00:00:00.000Z",
    )
    att = [("trajectory.json", "application/json", json.dumps(LOG_TRAJECTORY).encode())]
    return write_run(path, meta, t, pos, cur, attachments=att if trajectory else ())


@pytest.fixture(scope="session")
def sim_log(world: World) -> Callable[..., Path]:
    """:func:`write_sim_log` of the TX-40 world: ``sim_log(path, which, payload, seed, ...)``."""
    return partial(write_sim_log, world)


@pytest.fixture(scope="session")
def run_logs(world: World, sim_log: Callable[..., Path]) -> Callable[..., dict[str, Path]]:
    """Simulated logs ``{key}.mcap`` in a folder of runs a (unloaded, excitation 0), b (the
    calibrated payload, excitation 1) and c (the validation payload, excitation 2):
    ``run_logs(folder, {"a": seed, "b": seed, ...}, seconds=..., **sim_log options)``."""
    runs = {"a": (0, None), "b": (1, world.payload), "c": (2, world.validation)}

    def make(folder: Path, seeds: dict[str, int], **kw: Any) -> dict[str, Path]:
        return {
            key: sim_log(folder / f"{key}.mcap", runs[key][0], runs[key][1], seed, **kw)
            for key, seed in seeds.items()
        }

    return make


@pytest.fixture(scope="session")
def exact_run(world: World, simulate_exact: Callable[..., PreparedRun]) -> Simulate:
    """A noise-free run with exact derivatives (no filter), prepared for the estimators."""

    def make(
        which: int,
        payload: Payload | None,
        *,
        friction: WristFriction = WristFriction.PHYSICAL,
        duration: float = 10.0,
        rate: float = 50.0,
        label: str = "run",
    ) -> PreparedRun:
        t = np.arange(0.0, duration, 1.0 / rate)
        q, qd, qdd = world.excitations[which].evaluate(t)[:3]
        return simulate_exact(
            world.model,
            world.truth,
            world.columns,
            t,
            q,
            qd,
            qdd,
            label=label,
            payload=payload,
            friction=friction,
            period_s=1.0 / BASE_HZ,
        )

    return make


@pytest.fixture(scope="session")
def noisy_run(world: World) -> Simulate:
    """A run with torque noise and encoder quantisation, filtered and decimated like real data."""

    def make(
        which: int,
        payload: Payload | None,
        rng: np.random.Generator,
        *,
        duration: float = 40.0,
        rate: float = 250.0,
        torque_noise: float | np.ndarray = TORQUE_NOISE,
        current_noise: float | np.ndarray = 0.0,
        label: str = "run",
        sign_cutoff_hz: float | None = None,
    ) -> PreparedRun:
        t = np.arange(0.0, duration, 1.0 / rate)
        sim = simulate_noisy(
            world,
            which,
            payload,
            t,
            rng,
            torque_noise=torque_noise,
            current_noise=current_noise,
        )
        settings = default_filter(rate, BASE_HZ * HARMONICS, sign_cutoff_hz=sign_cutoff_hz)
        return prepare_recording(
            world.model,
            world.columns,
            label=label,
            q=sim.q,
            current=sim.current_reference,
            rate_hz=rate,
            settings=settings,
            payload=payload,
            period_s=1.0 / BASE_HZ,
        )

    return make


@pytest.fixture(scope="session")
def real_log(tx40_real: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The real TX-40 recording (../shared) converted once to a log, as a user would."""
    return convert_csv(
        tx40_real / "pos_read_data.csv",
        tx40_real / "curr_data.csv",
        5000.0,
        resource_path("tx40.toml"),
        motor_side=True,
        torque=True,
        out=tmp_path_factory.mktemp("tx40-real") / "tx40-real.mcap",
    )
