"""The simulated TX-40 of the validation study, and its simulated recordings.

The robot follows the shipped optimised excitation exactly (inverse dynamics, no bus); the
scenario's noise enters through the current references and the positions are quantised like an
encoder's. The recordings then go through the normal filtering and decimation path of
:mod:`drivegain.identify.prepare`, as a real log would.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from drivegain.config import load_payload, load_robot, load_truth, resource_path
from drivegain.config.payload import Payload
from drivegain.config.robot import Robot, WristFriction
from drivegain.config.truth import Truth
from drivegain.dynamics.base import BaseParameters
from drivegain.dynamics.model import RobotModel, build_model
from drivegain.excite.limits import check_limits
from drivegain.excite.optimise import ExcitationSettings, Problem, random_trajectory
from drivegain.excite.trajectory import load_trajectory
from drivegain.formats.fourier import FourierTrajectory
from drivegain.identify.columns import bases_for_forms, stored_columns
from drivegain.identify.prepare import PreparedRun, prepare_recording
from drivegain.identify.signal import FilterSettings, default_filter
from drivegain.identify.synth import simulate_run
from drivegain.validation.scenarios import (
    QUANTUM,
    RANDOM_BASE_HZ,
    RANDOM_HARMONICS,
    RANDOM_PERIODS,
    RATE_HZ,
    Scenario,
)


@dataclass(frozen=True)
class Tx40:
    """The simulated TX-40 every study and test world is built on.

    Attributes
    ----------
    robot, model, truth
        The TX-40 robot file, its Pinocchio model and the simulation truth.
    payload, validation
        The 4.59 kg payload of run b and the 1.686 kg payload of run c.
    bases
        Base parameters for each coupled-wrist friction form.
    columns
        Regressor columns stored by the preparation.
    """

    robot: Robot
    model: RobotModel
    truth: Truth
    payload: Payload
    validation: Payload
    bases: dict[WristFriction, BaseParameters]
    columns: tuple[str, ...]

    def parts(self) -> dict[str, Any]:
        """The fields by name (not copied), to build a world that extends this one."""
        return {f.name: getattr(self, f.name) for f in fields(Tx40)}


def load_tx40() -> Tx40:
    """Load the shipped TX-40 robot file, its simulation truth and both payloads."""
    robot = load_robot(resource_path("tx40.toml"))
    model = build_model(robot)
    bases = bases_for_forms(model)
    return Tx40(
        robot=robot,
        model=model,
        truth=load_truth(resource_path("sim/tx40-truth.toml")),
        payload=load_payload(resource_path("payloads/calibrated-4590g.toml"), robot.n),
        validation=load_payload(resource_path("payloads/validation-1686g.toml"), robot.n),
        bases=bases,
        columns=stored_columns(robot, bases, [6]),
    )


@dataclass(frozen=True)
class World(Tx40):
    """Everything fixed across seeds: the TX-40 (:class:`Tx40`), trajectory, filter.

    Attributes
    ----------
    fourier, trajectory_json
        The shipped excitation, parsed and as the bytes of its file (attached to the logs).
    rate_hz
        Sample rate of the recordings, Hz.
    settings
        Filter and decimation settings of the preparation.
    t, q, qd, qdd
        Sample times (s) and the exact trajectory, (N, n): rad, rad/s, rad/s².
    mask_auto
        Prepare the runs as ``identify --reversal-mask auto`` does
        (:func:`~drivegain.validation.estimators.run_designs`); False: as ``settings`` say.
    """

    fourier: FourierTrajectory
    trajectory_json: bytes
    rate_hz: float
    settings: FilterSettings
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    mask_auto: bool = False

    @property
    def form(self) -> WristFriction:
        """The robot file's coupled-wrist friction form (the one the estimators use)."""
        return self.robot.wrist_friction

    @property
    def base(self) -> BaseParameters:
        """Base parameters of :attr:`form`."""
        return self.bases[self.form]


def make_world(rate_hz: float = RATE_HZ) -> World:
    """Load the TX-40, its simulation truth, both payloads and the shipped excitation.

    Parameters
    ----------
    rate_hz
        Sample rate of the simulated recordings, Hz.
    """
    tx40 = load_tx40()
    traj_path = resource_path("tx40-excitation.json")
    excitation = load_trajectory(traj_path)
    excitation.check_robot(tx40.robot)
    fourier = excitation.fourier
    t = np.arange(0.0, fourier.duration_s, 1.0 / rate_hz)
    q, qd, qdd, _ = fourier.evaluate(t)
    bandwidth = fourier.base_frequency_hz * fourier.harmonics
    return World(
        **tx40.parts(),
        fourier=fourier,
        trajectory_json=Path(str(traj_path)).read_bytes(),
        rate_hz=rate_hz,
        settings=default_filter(rate_hz, bandwidth),
        t=t,
        q=q,
        qd=qd,
        qdd=qdd,
    )


def with_trajectory(world: World, fourier: FourierTrajectory) -> World:
    """``world`` following ``fourier`` instead: its samples and a filter for its bandwidth.

    Raises
    ------
    TrajectoryError
        If a sample of ``fourier`` breaks a limit of the robot file.
    """
    t = np.arange(0.0, fourier.duration_s, 1.0 / world.rate_hz)
    q, qd, qdd, qddd = fourier.evaluate(t)
    check_limits(world.robot, q, qd, qdd, qddd, label="random excitation", times=t)
    bandwidth = fourier.base_frequency_hz * fourier.harmonics
    return replace(
        world,
        fourier=fourier,
        trajectory_json=b"",
        # the filters follow the trajectory's bandwidth; the reversal mask is the world's choice
        settings=default_filter(
            world.rate_hz,
            bandwidth,
            reversal_mask_s=world.settings.reversal_mask_s,
            reversal_mask_drives=world.settings.reversal_mask_drives,
        ),
        t=t,
        q=q,
        qd=qd,
        qdd=qdd,
    )


def random_excitation(world: World, rng: np.random.Generator) -> FourierTrajectory:
    """A random, non-optimised excitation inside the robot's working limits.

    Drawn as the excitation optimiser draws its starting points
    (:meth:`drivegain.excite.optimise.Problem.random_start`: offsets in the middle half of each
    working range, coefficients with a 1/l spectrum, scaled to 90 % of the largest feasible
    amplitude, then made rigorously feasible): :data:`RANDOM_HARMONICS` harmonics at
    :data:`RANDOM_BASE_HZ` Hz for :data:`RANDOM_PERIODS` periods. No criterion is optimised.
    """
    settings = ExcitationSettings(
        base_frequency_hz=RANDOM_BASE_HZ, harmonics=RANDOM_HARMONICS, periods=RANDOM_PERIODS
    )
    return random_trajectory(Problem(world.robot, settings), rng)


@dataclass(frozen=True)
class SimRun:
    """One simulated recording: what a log holds.

    Attributes
    ----------
    label
        Run name (``unloaded``, ``loaded``, ``validation``).
    payload
        Payload carried, or ``None``.
    q
        Quantised joint positions, (N, n), rad.
    current
        Current references, (N, n), A.
    current_delay
        Age of the current samples relative to the positions, samples (what a user who knows
        the drives gives ``identify --current-delay``).
    """

    label: str
    payload: Payload | None
    q: np.ndarray
    current: np.ndarray
    current_delay: float = 0.0


def simulate(
    world: World, payload: Payload | None, scenario: Scenario, rng: np.random.Generator, label: str
) -> SimRun:
    """Run the excitation once: the scenario's noise in the currents, encoder quantisation."""
    rated = np.array([j.rated_current for j in world.robot.joints])
    sim = simulate_run(
        world.model,
        world.truth,
        world.q,
        world.qd,
        world.qdd,
        payload=payload,
        torque_noise=scenario.torque_noise,
        current_noise=scenario.current_fraction * rated,
        quantum=QUANTUM,
        rng=rng,
    )
    return SimRun(label=label, payload=payload, q=sim.q, current=sim.current_reference)


def prepare(world: World, run: SimRun) -> PreparedRun:
    """The normal path: filters, derivatives from quantised positions, parallel decimation; the
    excitation's period and start known, as a drivegain log gives them (its TRAJ.json
    attachment, its ``phase excitation`` event)."""
    prepared = prepare_recording(
        world.model,
        world.columns,
        label=run.label,
        q=run.q,
        current=run.current,
        rate_hz=world.rate_hz,
        settings=replace(world.settings, current_delay=run.current_delay),
        payload=run.payload,
        period_s=world.fourier.period_s,
    )
    # every run starts at the excitation's time 0, as the acquisition's event marks it
    return replace(prepared, phase_origin_s=0.0)


def simulate_three(world: World, scenario: Scenario, rng: np.random.Generator) -> list[SimRun]:
    """Runs a (unloaded), b (4.59 kg) and c (1.686 kg), independent noise from ``rng``.

    The order of the draws is part of the seeded results: a, then b, then c.
    """
    return [
        simulate(world, None, scenario, rng, "unloaded"),
        simulate(world, world.payload, scenario, rng, "loaded"),
        simulate(world, world.validation, scenario, rng, "validation"),
    ]
