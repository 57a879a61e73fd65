"""Optimisation of the Fourier coefficients (SLSQP, multi-start, seeded, with a budget).

Variables: per joint ``[q0, a_1..a_H, b_1..b_H]``. Constraints: every working limit (position
range with margin, velocity, acceleration, jerk) on a uniform grid over one period; they are
linear in the variables (:func:`~drivegain.excite.limits.grid_constraints`). After SLSQP, the
result is verified rigorously over continuous time (:func:`~drivegain.excite.limits.fourier_usage`)
and its amplitudes are scaled down if a bound is exceeded anywhere, so every returned trajectory
is feasible.

Gradient: the criteria give ``dF/dW_std``; the regressor's derivatives with respect to each
joint's position, velocity and acceleration at every sample are taken by forward differences
(one perturbed copy of the samples per joint and quantity, evaluated in a single vectorised
regressor call; the Coulomb columns, whose derivative is zero almost everywhere, are masked).
Then the chain rule through the Fourier basis gives dF/dθ at the cost of 1 + 3n regressor
evaluations, against 1 + n(1 + 2H) for finite differences of F.

Reproducibility: a start is fully determined by the seed and its index, and the budget sets the
number of starts and the iteration limit *deterministically* (:func:`plan_budget`), so the same
seed and budget give the same result on the same platform whatever the machine load and the
number of workers. The command's hard wall-clock cap (four times the budget) only skips starts
that have not begun, and then says so.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field

import numpy as np

from drivegain.config.excitation import DEFAULT_BASE_FREQUENCY_HZ, DEFAULT_HARMONICS
from drivegain.config.payload import Payload
from drivegain.config.robot import Robot
from drivegain.dynamics.model import build_model
from drivegain.dynamics.regressor import standard_regressor
from drivegain.errors import InputError, TrajectoryError
from drivegain.excite.criteria import (
    Criterion,
    DesignModel,
    WtlsDesign,
    base_criterion,
    design_model,
    observation_matrix,
    scaled_cond,
    wtls_criterion,
    wtls_design,
)
from drivegain.excite.limits import ExcitationLimits, fourier_usage, grid_constraints
from drivegain.formats.fourier import FourierTrajectory, basis
from drivegain.scipyimport import import_scipy

# scipy.optimize without its import-time docstring rewriting (see drivegain.scipyimport)
scipy_optimize = import_scipy("scipy.optimize")

log = logging.getLogger(__name__)

#: Seconds of budget per start. A start of the default TX-40 problem (with the WTLS criterion)
#: costs about 6 s of one core: 3 s of wall time per start with 2 workers on a free 2-core
#: machine, up to about 7 s when other work shares it (measured by benchmarks/bench_excite.py).
#: 8 s keeps the command within its budget on the shared 2-core reference machine. Only used to
#: turn a budget into a deterministic number of starts (:func:`plan_budget`).
NOMINAL_START_S = 8.0
#: SLSQP iteration limit of a start.
MAX_ITER = 150
#: Samples per period of the criterion and of the constraint grid during optimisation.
CRITERION_SAMPLES = 150
CONSTRAINT_SAMPLES = 200
#: Forward-difference steps for the regressor derivatives (rad, rad/s, rad/s²).
FD_STEP = (1e-6, 1e-6, 1.0)  # W is linear in qdd: any step is exact there


@dataclass(frozen=True)
class ExcitationSettings:
    """What to optimise.

    Attributes
    ----------
    base_frequency_hz, harmonics, periods
        The series (contracts §6).
    criterion
        ``cond`` or ``logdet`` on the base observation matrix.
    payload
        Adds the WTLS criterion for this payload (``None``: base criterion only).
    chi_nominal
        Nominal standard parameters for the WTLS criterion's currents (needed with a payload).
    wtls_weight
        Weight of ``log cond`` of W_tot added to the base criterion.
    position_margin, fraction
        Working limits (:class:`~drivegain.excite.limits.ExcitationLimits`).
    seed
        Seed of the starts.
    starts, max_iter
        Number of starts and SLSQP iteration limit (see :func:`plan_budget`).
    wall_cap_s
        Hard wall-clock cap; starts not begun by then are skipped (result flagged).
    jobs
        Worker processes.
    """

    base_frequency_hz: float = DEFAULT_BASE_FREQUENCY_HZ
    harmonics: int = DEFAULT_HARMONICS
    periods: int = 3
    criterion: Criterion = Criterion.COND
    payload: Payload | None = None
    chi_nominal: np.ndarray | None = None
    wtls_weight: float = 1.0
    position_margin: float = 0.1
    fraction: float = 0.95
    seed: int = 0
    starts: int = 8
    max_iter: int = MAX_ITER
    wall_cap_s: float | None = None
    jobs: int = 1


def plan_budget(budget_s: float) -> tuple[int, int]:
    """Deterministic (starts, max_iter) for a budget in seconds.

    Independent of the machine and of the number of workers, so that the same seed and budget
    give the same trajectory anywhere: one start per :data:`NOMINAL_START_S` seconds; a budget
    shorter than one start cuts the iterations instead.
    """
    if not budget_s > 0.0:
        raise InputError(f"must be > 0 s, got {budget_s}", key="budget")
    if budget_s < NOMINAL_START_S:
        return 1, max(10, int(MAX_ITER * budget_s / NOMINAL_START_S))
    return int(budget_s / NOMINAL_START_S), MAX_ITER


@dataclass
class StartResult:
    """Outcome of one start."""

    index: int
    coefficients: np.ndarray
    objective: float
    initial_objective: float
    initial_cond: float
    cond: float
    iterations: int
    message: str
    scale: float
    seconds: float


@dataclass
class OptimisationResult:
    """The best trajectory over all starts, and what the starts did."""

    fourier: FourierTrajectory
    objective: float
    starts: list[StartResult]
    skipped: int
    seconds: float
    metrics: dict[str, float] = field(default_factory=dict)
    #: the criteria's model, built in this process while the workers ran (for the metrics)
    design: DesignModel | None = None

    @property
    def random_conds(self) -> np.ndarray:
        """cond of the random feasible initial trajectories of every start."""
        return np.array([s.initial_cond for s in self.starts])


class Problem:
    """Objective, gradient and constraints for one robot and settings (built once per worker)."""

    def __init__(
        self, robot: Robot, settings: ExcitationSettings, design: DesignModel | None = None
    ):
        self.robot = robot
        self.settings = settings
        self.limits = ExcitationLimits.from_robot(
            robot, settings.position_margin, settings.fraction
        )
        self.design = design if design is not None else design_model(build_model(robot))
        self.wtls: WtlsDesign | None = None
        if settings.payload is not None:
            if settings.chi_nominal is None:
                raise TrajectoryError("the WTLS criterion needs nominal dynamic parameters")
            self.wtls = wtls_design(robot, settings.chi_nominal, settings.payload)
        self.n = robot.n
        self.h = settings.harmonics
        self.p = 1 + 2 * self.h
        self.omega = 2.0 * np.pi * settings.base_frequency_hz
        period = 1.0 / settings.base_frequency_hz
        t = np.arange(CRITERION_SAMPLES) * period / CRITERION_SAMPLES
        self.b = [basis(t, self.omega, self.h, k) for k in range(3)]
        tc = np.arange(CONSTRAINT_SAMPLES) * period / CONSTRAINT_SAMPLES
        self.g, self.hvec = grid_constraints(tc, self.omega, self.h, self.limits)
        self._cache: tuple[bytes, float, np.ndarray] | None = None

    # -- objective -------------------------------------------------------------------------
    def states(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        th = theta.reshape(self.n, self.p)
        return self.b[0] @ th.T, self.b[1] @ th.T, self.b[2] @ th.T

    def criterion_of(self, w_std: np.ndarray) -> tuple[float, np.ndarray]:
        """Combined criterion value and gradient with respect to ``w_std``."""
        f, g = base_criterion(self.design, w_std, self.settings.criterion)
        if self.wtls is not None and self.settings.wtls_weight > 0.0:
            fw, gw = wtls_criterion(self.design, self.wtls, w_std)
            f += self.settings.wtls_weight * fw
            g += self.settings.wtls_weight * gw
        return f, g

    def value(self, theta: np.ndarray) -> float:
        """Objective without gradient (line searches need only this)."""
        if self._cache is not None and self._cache[0] == theta.tobytes():
            return self._cache[1]
        w = standard_regressor(self.design.model, *self.states(theta))
        return self.criterion_of(w)[0]

    def value_and_grad(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        key = theta.tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1], self._cache[2]
        q, qd, qdd = self.states(theta)
        m, n = q.shape[0], self.n
        blocks = 1 + 3 * n
        # Copy 0 is the trajectory; copy 1 + 3j + k has joint j's quantity k perturbed.
        qs = np.tile(q, (blocks, 1)).reshape(blocks, m, n)
        qds = np.tile(qd, (blocks, 1)).reshape(blocks, m, n)
        qdds = np.tile(qdd, (blocks, 1)).reshape(blocks, m, n)
        for j in range(n):
            qs[1 + 3 * j, :, j] += FD_STEP[0]
            qds[2 + 3 * j, :, j] += FD_STEP[1]
            qdds[3 + 3 * j, :, j] += FD_STEP[2]
        w_all = standard_regressor(
            self.design.model, qs.reshape(-1, n), qds.reshape(-1, n), qdds.reshape(-1, n)
        ).reshape(blocks, m, n, -1)
        w0 = w_all[0]
        f, gw = self.criterion_of(w0)
        diff = w_all[1:] - w0[None]
        diff[..., self.design.sign_columns] = 0.0
        # gx[c, s] = sum over rows i and params k of dF/dW[s, i, k] * dW[s, i, k]/dx_c
        gx = np.einsum("sik,csik->cs", gw, diff).reshape(n, 3, m)
        gx /= np.asarray(FD_STEP)[None, :, None]
        grad = np.empty((n, self.p))
        for j in range(n):
            grad[j] = sum(self.b[k].T @ gx[j, k] for k in range(3))
        out = (f, grad.reshape(-1))
        self._cache = (key, out[0], out[1])
        return out

    # -- starts ----------------------------------------------------------------------------
    def feasible_scale(self, theta: np.ndarray) -> float:
        """Largest factor <= 1 on the amplitudes keeping the grid constraints satisfied."""
        th = theta.reshape(self.n, self.p)
        centre = th.copy()
        centre[:, 1:] = 0.0
        base = self.g @ centre.reshape(-1)
        var = self.g @ (th - centre).reshape(-1)
        room = self.hvec - base
        if np.any(room < 0):
            raise TrajectoryError("the offsets q0 are outside the working position range")
        with np.errstate(divide="ignore"):
            ratios = np.where(var > 0, room / var, np.inf)
        return float(min(1.0, ratios.min()))

    def random_start(self, rng: np.random.Generator) -> np.ndarray:
        """A random feasible trajectory: offsets in the middle half of each working range,
        coefficients with a 1/l spectrum, scaled to 90 % of the largest feasible amplitude."""
        lo, hi = self.limits.lower, self.limits.upper
        mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        th = np.zeros((self.n, self.p))
        th[:, 0] = mid + rng.uniform(-0.5, 0.5, self.n) * half
        decay = 1.0 / np.arange(1, self.h + 1)
        th[:, 1 : 1 + self.h] = rng.normal(size=(self.n, self.h)) * decay
        th[:, 1 + self.h :] = rng.normal(size=(self.n, self.h)) * decay
        flat = th.reshape(-1)
        centre = th.copy()
        centre[:, 1:] = 0.0
        # Scale to the boundary (the scale can exceed 1 when the draw is small).
        var = self.g @ (flat - centre.reshape(-1))
        room = self.hvec - self.g @ centre.reshape(-1)
        with np.errstate(divide="ignore"):
            s = float(np.where(var > 0, room / var, np.inf).min())
        th[:, 1:] *= 0.9 * s
        return th.reshape(-1)

    def repair(self, theta: np.ndarray) -> tuple[np.ndarray, float]:
        """Make ``theta`` rigorously feasible: clip q0 into range, scale the amplitudes down.

        Returns the feasible coefficients and the scale applied.
        """
        th = theta.reshape(self.n, self.p).copy()
        th[:, 0] = np.clip(th[:, 0], self.limits.lower + 1e-6, self.limits.upper - 1e-6)
        fourier = FourierTrajectory.from_coefficients(self.settings.base_frequency_hz, th)
        usage = fourier_usage(fourier, self.limits).worst
        scale = 1.0
        if usage > 1.0:
            # A hair below the bound so that round-off cannot put it back above.
            scale = (1.0 - 1e-9) / usage
            th[:, 1:] *= scale
        return th.reshape(-1), scale

    def cond(self, theta: np.ndarray) -> float:
        """Scaled cond of the base observation matrix on the criterion grid."""
        w = standard_regressor(self.design.model, *self.states(theta))
        return scaled_cond(observation_matrix(self.design, w))

    def run_start(self, index: int, deadline: float | None = None) -> StartResult:
        """One start: seeded random feasible point, SLSQP, rigorous repair."""
        t0 = time.perf_counter()
        rng = np.random.default_rng([self.settings.seed, index])
        x0 = self.random_start(rng)
        initial_cond = self.cond(x0)
        initial_objective = self.value(x0)
        constraints = {
            "type": "ineq",
            "fun": lambda x: self.hvec - self.g @ x,
            "jac": lambda x: -self.g,
        }
        res = scipy_optimize.minimize(
            self.value,
            x0,
            jac=lambda x: self.value_and_grad(x)[1],
            method="SLSQP",
            constraints=[constraints],
            options={"maxiter": self.settings.max_iter, "ftol": 1e-7},
        )
        x = res.x if np.all(np.isfinite(res.x)) else x0
        x, scale = self.repair(x)
        return StartResult(
            index=index,
            coefficients=x,
            objective=self.value(x),
            initial_objective=initial_objective,
            initial_cond=initial_cond,
            cond=self.cond(x),
            iterations=int(res.nit),
            message=str(res.message),
            scale=scale,
            seconds=time.perf_counter() - t0,
        )


# -- multi-start driver (worker processes) ---------------------------------------------------
_WORKER: Problem | None = None


def _init_worker(robot: Robot, settings: ExcitationSettings) -> None:
    global _WORKER
    _WORKER = Problem(robot, settings)


def _run_in_worker(index: int) -> StartResult:
    assert _WORKER is not None
    return _WORKER.run_start(index)


Progress = Callable[[StartResult, StartResult], None]

#: BLAS threading variables pinned to 1 in the workers.
_BLAS_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def optimise(
    robot: Robot,
    settings: ExcitationSettings,
    progress: Progress | None = None,
    *,
    in_process: bool = False,
) -> OptimisationResult:
    """Optimise an excitation trajectory over ``settings.starts`` seeded starts.

    Starts run in ``settings.jobs`` worker processes started with "spawn" and single-threaded
    BLAS: multi-threaded BLAS on small matrices is much slower on busy cores, and its
    round-off depends on the thread count, which would make the result depend on the machine
    load. Each start is independent of the worker it runs in, so the result does not depend on
    ``jobs`` either.

    Parameters
    ----------
    robot
        The robot.
    settings
        What to optimise (starts, iterations, seed, criterion, payload...).
    progress
        Called after each start with (that start, the best so far).
    in_process
        Run the starts in this process instead (BLAS threading as it is here).

    Raises
    ------
    ConfigError
        Working limits impossible for this robot (see
        :meth:`~drivegain.excite.limits.ExcitationLimits.from_robot`).
    """
    # Fail on impossible limits here, not in a worker.
    ExcitationLimits.from_robot(robot, settings.position_margin, settings.fraction)
    t0 = time.perf_counter()
    cap = settings.wall_cap_s
    results: list[StartResult] = []
    best: StartResult | None = None
    skipped = 0

    def accept(r: StartResult) -> None:
        nonlocal best
        results.append(r)
        if best is None or (r.objective, r.index) < (best.objective, best.index):
            best = r
        if progress is not None:
            progress(r, best)

    def over_cap() -> bool:
        return cap is not None and time.perf_counter() - t0 > cap

    design: DesignModel | None = None
    if in_process:
        prob = Problem(robot, settings)
        design = prob.design
        for i in range(settings.starts):
            if i > 0 and over_cap():
                skipped = settings.starts - i
                break
            accept(prob.run_start(i))
    else:
        jobs = max(1, min(settings.jobs, settings.starts))
        ctx = multiprocessing.get_context("spawn")
        saved = {k: os.environ.get(k) for k in _BLAS_ENV}
        os.environ.update(dict.fromkeys(_BLAS_ENV, "1"))  # inherited by the spawned workers
        try:
            with ProcessPoolExecutor(
                max_workers=jobs,
                mp_context=ctx,
                initializer=_init_worker,
                initargs=(robot, settings),
            ) as pool:
                pending = list(range(settings.starts))
                running: dict[Future[StartResult], int] = {}
                # Submit as workers free up, so that the wall-clock cap can still skip starts.
                while pending and len(running) < jobs:
                    i = pending.pop(0)
                    running[pool.submit(_run_in_worker, i)] = i
                # The metrics need the same model (seconds of QR): built here while the workers
                # start and run, instead of after them.
                design = design_model(build_model(robot))
                while running:
                    done, _ = wait(running, return_when=FIRST_COMPLETED)
                    for fut in sorted(done, key=lambda f: running[f]):
                        del running[fut]
                        accept(fut.result())
                    while pending and len(running) < jobs:
                        if over_cap():
                            skipped += len(pending)
                            pending.clear()
                            break
                        i = pending.pop(0)
                        running[pool.submit(_run_in_worker, i)] = i
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    if best is None:
        raise TrajectoryError("no optimisation start completed")
    theta = best.coefficients.reshape(robot.n, -1)
    fourier = FourierTrajectory.from_coefficients(
        settings.base_frequency_hz, theta, settings.periods
    )
    results.sort(key=lambda r: r.index)
    return OptimisationResult(
        fourier=fourier,
        objective=best.objective,
        starts=results,
        skipped=skipped,
        seconds=time.perf_counter() - t0,
        design=design,
    )


def random_trajectory(problem: Problem, rng: np.random.Generator) -> FourierTrajectory:
    """A random feasible trajectory as the starts use (for comparisons)."""
    theta, _ = problem.repair(problem.random_start(rng))
    return FourierTrajectory.from_coefficients(
        problem.settings.base_frequency_hz,
        theta.reshape(problem.n, problem.p),
        problem.settings.periods,
    )
