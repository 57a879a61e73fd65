"""Closed-loop recordings: the simulated cell's drives and forward dynamics, without the bus.

The exact-tracking scenarios of :mod:`~drivegain.validation.world` compute the currents by
inverse dynamics along the trajectory, so the noise never reaches the motion. Here the robot is
driven as the simulated cell drives it (:mod:`drivegain.drivers.physics`): at every SYNC of the
recording the next setpoint of the trajectory is latched (CSP, linear interpolation over one
period with velocity feed-forward), the cascaded position/velocity loops compute the current
references from quantised motor encoders, the current loop adds its error, the true dynamics
integrate the motion. What a drive reports is recorded: motor encoder counts at the SYNC and the
current reference averaged over the period that just ended, in steps of 0.1 % of the rated
current (the TPDO's resolution). The tracking error, the noise fed back through the loops and
the offset of the averaged currents are all in the data, as in a real log; the runs state that
offset (:func:`current_delay`) as a user who knows the drives states it to ``identify``.

The CAN stack is left out: the lockstep acquisition of one 30 s run costs minutes, this costs
seconds (see docs/validation.md for the measured time per seed).
"""

from __future__ import annotations

import numpy as np

from drivegain.config.payload import Payload
from drivegain.drivers.physics import (
    Dynamics,
    MotorMode,
    RobotPhysics,
    design_gains,
    truth_parameters,
)
from drivegain.validation.scenarios import (
    CELL_STEP_S,
    LEAD_IN_S,
    LOOP_BANDWIDTH_HZ,
    LOOP_STEP_S,
    Scenario,
)
from drivegain.validation.world import SimRun, World

#: Resolution of the reported current, fraction of the rated current (TPDO in per mille).
CURRENT_STEP = 1e-3


def current_delay(substeps: int) -> float:
    """Age of the recorded currents relative to the positions, samples.

    Half a period for the mean over the period that ends at the position sample, plus half an
    internal step: the semi-implicit Euler step applies a step's current over the whole step
    that follows the time it was computed for.
    """
    return 0.5 + 0.5 / substeps


def closed_loop_run(
    world: World, payload: Payload | None, scenario: Scenario, rng: np.random.Generator, label: str
) -> SimRun:
    """One recording of ``world``'s trajectory by the closed-loop drives.

    Parameters
    ----------
    world
        The robot, its truth, the trajectory and the sample rate.
    payload
        Payload carried, or ``None``.
    scenario
        Its ``loop_noise_nm`` (N·m per internal step) is the current-loop error of every drive;
        its ``current_fraction`` adds white noise (fraction of rated current) to the reported
        currents.
    rng
        Random generator of the noise.
    label
        Run name.

    Returns
    -------
    SimRun
        Joint positions from the motor encoders (rad) and reported currents (A), one row per
        sample of ``world.t``.

    The drives start on the trajectory (position and velocity) :data:`LEAD_IN_S` before the
    recording and track it from there, so the loops' start-up transient is not recorded.
    """
    robot = world.robot
    n = robot.n
    period = 1.0 / world.rate_hz
    substeps = max(2, round(period / LOOP_STEP_S))
    lead = round(LEAD_IN_S * world.rate_hz)
    # Setpoint times: the lead-in, the recording, and one more period (the last latch).
    times = (np.arange(-lead, world.t.size + 1)) * period
    q_set, qd_set, _, _ = world.fourier.evaluate(times)
    dyn = Dynamics(robot, truth_parameters(robot, world.truth, payload), world.form)
    gains = world.truth.gains
    loop = design_gains(robot, dyn, gains, q_set[0], bandwidth_hz=LOOP_BANDWIDTH_HZ)
    dt = period / substeps
    # White noise per step: the same density as the cell's at its own (shorter) step.
    noise = scenario.loop_noise_nm * np.sqrt(CELL_STEP_S / dt)
    ph = RobotPhysics(robot, dyn, gains, loop, dt, q_set[0], noise, rng)
    ph.qd = qd_set[0].copy()
    for motor in range(n):
        ph.set_mode(motor, MotorMode.TRACK)
    k = robot.transmission()
    kinv = np.linalg.inv(k)
    cpr = np.array([j.encoder_counts for j in robot.joints], dtype=float) / (2 * np.pi)
    rated = np.array([j.rated_current for j in robot.joints])
    targets = q_set @ k.T
    everyone = np.ones(n, dtype=bool)
    q = np.empty((world.t.size, n))
    current = np.empty((world.t.size, n))
    for i in range(times.size - 1):
        row = i - lead
        counts = ph.encoder_counts()
        i_mean, _ = ph.take_period_means()
        if row >= 0:
            q[row] = kinv @ (counts / cpr)
            current[row] = i_mean
        ph.latch_targets(targets[i + 1], everyone, period)
        ph.advance(substeps)
    if scenario.current_fraction:
        current = current + rng.standard_normal(current.shape) * scenario.current_fraction * rated
    step = CURRENT_STEP * rated
    current = np.rint(current / step) * step
    return SimRun(
        label=label, payload=payload, q=q, current=current, current_delay=current_delay(substeps)
    )


def closed_loop_three(world: World, scenario: Scenario, rng: np.random.Generator) -> list[SimRun]:
    """Runs a (unloaded), b (4.59 kg) and c (1.686 kg) in closed loop, noise drawn in that order."""
    return [
        closed_loop_run(world, None, scenario, rng, "unloaded"),
        closed_loop_run(world, world.payload, scenario, rng, "loaded"),
        closed_loop_run(world, world.validation, scenario, rng, "validation"),
    ]
