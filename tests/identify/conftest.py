"""Fixtures of the identify tests: the TX-40, its simulation truth, payloads, excitations."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from drivegain.config import load_payload, load_robot, load_truth, resource_path
from drivegain.config.payload import Payload
from drivegain.config.robot import Robot, WristFriction
from drivegain.config.truth import Truth
from drivegain.dynamics.base import BaseParameters
from drivegain.dynamics.model import RobotModel, build_model
from drivegain.formats.fourier import FourierTrajectory
from drivegain.identify.blas import limited_blas_threads
from drivegain.identify.convert import convert_csv
from drivegain.identify.prepare import (
    PreparedRun,
    bases_for_forms,
    prepare_exact,
    prepare_recording,
    stored_columns,
)
from drivegain.identify.signal import default_filter
from drivegain.identify.synth import exciting_sum_of_sines, simulate_run

#: Excitation used by the simulated runs: base frequency and harmonics (bandwidth 1 Hz).
BASE_HZ = 0.2
HARMONICS = 5
#: Noise of model.md: torque noise, N·m, and the encoder quantum at the joint, rad.
TORQUE_NOISE = 0.05
QUANTUM = float(np.deg2rad(1e-3))


@dataclass(frozen=True)
class World:
    robot: Robot
    model: RobotModel
    truth: Truth
    payload: Payload
    validation: Payload
    bases: dict[WristFriction, BaseParameters]
    columns: tuple[str, ...]
    excitations: tuple[FourierTrajectory, FourierTrajectory, FourierTrajectory]


@pytest.fixture(scope="session", autouse=True)
def _single_blas_thread() -> Iterator[None]:
    """As the identify command does: OpenBLAS threads thrash on the shared, busy cores."""
    with limited_blas_threads(1):
        yield


@pytest.fixture(scope="session")
def world() -> World:
    robot = load_robot(resource_path("tx40.toml"))
    model = build_model(robot)
    bases = bases_for_forms(model)
    rng = np.random.default_rng(20120701)
    # Separate trajectories for runs a, b and the validation run, as recorded in practice.
    excitations = tuple(
        exciting_sum_of_sines(
            model,
            rng,
            base_frequency_hz=BASE_HZ,
            harmonics=HARMONICS,
            candidates=8,
            base=bases[WristFriction.PHYSICAL],
        )
        for _ in range(3)
    )
    return World(
        robot=robot,
        model=model,
        truth=load_truth(resource_path("sim/tx40-truth.toml")),
        payload=load_payload(resource_path("payloads/calibrated-4590g.toml")),
        validation=load_payload(resource_path("payloads/validation-1686g.toml")),
        bases=bases,
        columns=stored_columns(robot, bases, [6]),
        excitations=excitations,  # type: ignore[arg-type]
    )


Simulate = Callable[..., PreparedRun]


@pytest.fixture(scope="session")
def exact_run(world: World) -> Simulate:
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
        sim = simulate_run(world.model, world.truth, q, qd, qdd, payload=payload, friction=friction)
        return prepare_exact(
            world.model,
            world.columns,
            label=label,
            t=t,
            q=q,
            qd=qd,
            qdd=qdd,
            current=sim.current_reference,
            payload=payload,
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
    ) -> PreparedRun:
        t = np.arange(0.0, duration, 1.0 / rate)
        q, qd, qdd = world.excitations[which].evaluate(t)[:3]
        sim = simulate_run(
            world.model,
            world.truth,
            q,
            qd,
            qdd,
            payload=payload,
            torque_noise=torque_noise,
            current_noise=current_noise,
            quantum=QUANTUM,
            rng=rng,
        )
        settings = default_filter(rate, BASE_HZ * HARMONICS)
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
