"""Physically consistent identification: IDIM-WLS of the base parameters subject to every body
being a real rigid body (Wensing, Kim & Slotine 2017), solved as a semidefinite program.

The decision variables are the *standard* parameters χ (so the constraints can be written), the
fit is on their base combinations ``θ = B χ`` (B the regrouping matrix of
:class:`~drivegain.dynamics.base.BaseParameters`) and the payload parameters:

    minimise   ‖R [B χ; χ_L; g]‖² / ν  +  λ Σ_i ((χ_i − χ0_i) / s_i)²
    subject to J(χ_link j) ⪰ 0 for every link, J(χ_L) ⪰ 0 for every payload,
               Ia_j, Fv_j, Fc_j, fvm, fcm ≥ 0,   (optionally) s_j g_j ≥ 0,

with R the triangular factor of the row-weighted (1/σ_j) stacked rows ``[W_base | W_L | −V]``
(:mod:`drivegain.identify.design`), ν the weighted squared residual of the unconstrained fit (so
the objective is about 1 at the optimum), χ0 the a priori (CAD) parameters, s_i their scale, and
J the 4×4 pseudo-inertia matrix ``[[½ tr(I)·1 − I, h], [hᵀ, m]]`` of a body (I the inertia
tensor at the frame origin, h the first moments, m the mass): J ⪰ 0 exactly when a non-negative
mass distribution with these moments exists. λ is small by default: it only picks, among the
standard parameters with the same base combinations, those nearest the a priori ones.

cvxpy is imported inside :func:`fit_consistent` only: the command line does not pay for it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivegain.config.payload import PAYLOAD_PARAMS
from drivegain.config.robot import Robot
from drivegain.dynamics.base import BaseParameters
from drivegain.dynamics.params import N_INERTIAL, N_PER_JOINT, inertial_slice, n_standard
from drivegain.errors import IdentificationError, InputError
from drivegain.identify.cases import PayloadEstimate
from drivegain.identify.crossval import split_runs
from drivegain.identify.design import Design, stacked_factor
from drivegain.identify.predict import prediction_quality, predictions

#: Gain handling of the consistent fit: keep the given/identified gains, or solve them jointly
#: (needs a loaded run with a known payload mass) with a sign constraint.
GAIN_MODES = ("fixed", "apriori-sign", "positive")
#: Default weight λ of the pull towards the a priori parameters (relative to the normalised fit).
DEFAULT_PRIOR_WEIGHT = 1e-6
#: A PSD constraint is active when its smallest eigenvalue is below this fraction of its largest;
#: a bound when the value is below this fraction of its scale.
ACTIVE_TOL = 1e-6
#: Scale floor per kind of standard parameter (SI units), for the regularisation and variables.
SCALE_FLOOR = {
    "XX": 1e-3,
    "XY": 1e-3,
    "XZ": 1e-3,
    "YY": 1e-3,
    "YZ": 1e-3,
    "ZZ": 1e-3,
    "MX": 1e-2,
    "MY": 1e-2,
    "MZ": 1e-2,
    "M": 0.1,
    "Ia": 1e-3,
    "Fv": 0.1,
    "Fc": 0.1,
    "OFF": 0.1,
    "fvm": 0.1,
    "fcm": 0.1,
}
_KINDS = (*PAYLOAD_PARAMS, "Ia", "Fv", "Fc", "OFF")
#: Per-joint parameters that must be non-negative (positions in the 14-parameter block).
NONNEGATIVE = ("Ia", "Fv", "Fc")


def pseudo_inertia_map() -> np.ndarray:
    """Linear map (16, 10): ``vec(J) = L @ [XX XY XZ YY YZ ZZ MX MY MZ M]`` (row-major vec).

    J = [[Σ, h], [hᵀ, m]] with Σ = ½ tr(I)·1 − I (kg·m²), h the first moments (kg·m), m (kg).
    """
    lmap = np.zeros((4, 4, 10))
    # Σ_xx = (−XX + YY + ZZ)/2, and cyclically; off-diagonals Σ_xy = −XY (tensor elements).
    diag = {0: (0, 3, 5), 1: (3, 0, 5), 2: (5, 0, 3)}
    for k, (own, a, b) in diag.items():
        lmap[k, k, own] = -0.5
        lmap[k, k, a] = 0.5
        lmap[k, k, b] = 0.5
    for (r, c), p in {(0, 1): 1, (0, 2): 2, (1, 2): 4}.items():
        lmap[r, c, p] = lmap[c, r, p] = -1.0
    for k in range(3):
        lmap[k, 3, 6 + k] = lmap[3, k, 6 + k] = 1.0
    lmap[3, 3, 9] = 1.0
    return lmap.reshape(16, 10)


_LMAP = pseudo_inertia_map()


def pseudo_inertia(inertial10: np.ndarray) -> np.ndarray:
    """The 4×4 pseudo-inertia matrix of ``[XX XY XZ YY YZ ZZ MX MY MZ M]`` (origin, tensor)."""
    return (_LMAP @ np.asarray(inertial10, dtype=float)).reshape(4, 4)


def pseudo_inertia_eigenvalues(inertial10: np.ndarray) -> np.ndarray:
    """Eigenvalues (ascending) of the pseudo-inertia matrix; all ≥ 0 for a real body."""
    return np.linalg.eigvalsh(pseudo_inertia(inertial10))


def parameter_scales(robot: Robot, prior: np.ndarray) -> np.ndarray:
    """Scale s_i of each standard parameter: ``max(|χ0_i|, floor of its kind)``."""
    floors = np.array(
        [SCALE_FLOOR[k] for _ in range(robot.n) for k in _KINDS]
        + [SCALE_FLOOR[k] for _ in robot.couplings for k in ("fvm", "fcm")]
    )
    return np.maximum(np.abs(prior), floors)


@dataclass(frozen=True)
class Constraint:
    """One constraint of the consistent fit at the solution.

    Attributes
    ----------
    name
        Body (``link3``, ``payload <name>``) or parameter (``Fv2``, ``g4``).
    kind
        ``pseudo_inertia`` (J ⪰ 0), ``nonnegative`` or ``gain_sign``.
    value
        Smallest eigenvalue of J (kg·m², kg·m or kg mixed), or the parameter's value (SI).
    active
        Whether the solution lies on the constraint's boundary.
    """

    name: str
    kind: str
    value: float
    active: bool


@dataclass(frozen=True)
class ConsistentFit:
    """The consistent identification on some runs.

    Attributes
    ----------
    standard
        Standard parameters χ (86 for the TX-40), SI units.
    base
        Their base combinations B χ.
    payloads
        Payload parameters (order of :data:`PAYLOAD_PARAMS`), one per loaded run.
    gains
        Gains used (fixed) or solved, N·m/A.
    gain_mode
        One of :data:`GAIN_MODES`.
    constraints
        Every constraint with its value and whether it is active.
    residual_norm, relative_error
        ‖Y − Ŷ‖ (N·m, unweighted) and ‖Y − Ŷ‖/‖Y‖ over all runs.
    r2, joint_relative
        Per joint R² and ‖ρ_j‖/‖Y_j‖.
    objective_ratio
        Weighted squared residual over that of the unconstrained fit (≥ 1; 1: no cost).
    status, solver, solve_time_s, setup_time_s
        Solver outcome, name, its own solve time and the problem building time (s).
    """

    standard: np.ndarray
    base: np.ndarray
    payloads: list[np.ndarray]
    gains: np.ndarray
    gain_mode: str
    constraints: list[Constraint]
    residual_norm: float
    relative_error: float
    r2: np.ndarray
    joint_relative: np.ndarray
    objective_ratio: float
    status: str
    solver: str
    solve_time_s: float
    setup_time_s: float

    @property
    def active(self) -> list[Constraint]:
        return [c for c in self.constraints if c.active]


def _transforms(designs: Sequence[Design], n_slots: int) -> list[np.ndarray]:
    """Per design T with ``D T u = W_b θ + W_L χ_L − V g`` for ``u = [θ; χ_L...; g]``."""
    out, slot = [], 0
    for d in designs:
        nb, n = d.nb, d.n
        t = np.zeros((d.m, nb + 10 * n_slots + n))
        t[:nb, :nb] = np.eye(nb)
        if d.loaded:
            t[nb : nb + 10, nb + 10 * slot : nb + 10 * (slot + 1)] = np.eye(10)
            slot += 1
        t[nb + 10 :, nb + 10 * n_slots :] = -np.eye(n)
        out.append(t)
    return out


def fit_consistent(
    designs: Sequence[Design],
    bp: BaseParameters,
    robot: Robot,
    gains: np.ndarray,
    sigma: np.ndarray,
    *,
    prior: np.ndarray | None = None,
    prior_weight: float = DEFAULT_PRIOR_WEIGHT,
    gain_mode: str = "fixed",
    factors: Sequence[np.ndarray] | None = None,
    solver: str = "CLARABEL",
) -> ConsistentFit:
    """Least squares of the base (and payload) parameters over physically consistent bodies.

    Parameters
    ----------
    designs
        The runs (one friction form's designs, as :func:`drivegain.identify.cases.fit_case`).
    bp
        Base parameters of that form (regrouping matrix and names).
    robot
        The robot description.
    gains
        Drive gains, N·m/A (fixed, or the a priori signs' reference in the other modes).
    sigma
        Row weights' σ_j per joint, N·m (the unconstrained fit's, for comparable objectives).
    prior
        A priori standard parameters χ0 (SI); None: zeros.
    prior_weight
        λ ≥ 0, weight of the pull towards ``prior``.
    gain_mode
        ``fixed``: use ``gains``. ``apriori-sign`` or ``positive``: solve the gains too, each of
        the a priori sign (or positive); needs a loaded run with known payload parameters.
    factors
        Per design, the R factors of every joint's rows (computed when not given).
    solver
        cvxpy solver name (``CLARABEL``, ``SCS``).

    Returns
    -------
    ConsistentFit
        Standard and base parameters, payloads, constraint activity and fit quality.

    Raises
    ------
    InputError
        Unknown gain mode, negative weight, or solved gains without a known payload parameter.
    IdentificationError
        The solver fails.
    """
    import cvxpy as cp

    t_setup = time.perf_counter()
    if gain_mode not in GAIN_MODES:
        raise InputError(f"expected one of {', '.join(GAIN_MODES)}, got {gain_mode!r}", key="gains")
    if not prior_weight >= 0.0:
        raise InputError(f"must be >= 0, got {prior_weight}", key="prior_weight")
    gains = np.asarray(gains, dtype=float)
    n, nb = robot.n, bp.n_base
    ns = n_standard(robot)
    loaded = [d for d in designs if d.loaded]
    n_slots = len(loaded)
    chi0 = np.zeros(ns) if prior is None else np.asarray(prior, dtype=float)
    if factors is None:
        factors = [d.factors() for d in designs]
    r = stacked_factor(factors, _transforms(designs, n_slots), 1.0 / np.asarray(sigma, float))
    k = nb + 10 * n_slots
    bmat = bp.matrix()
    scale = parameter_scales(robot, chi0)
    pay_nominal = [np.nan_to_num(d.run.payload.values) for d in loaded if d.run.payload]
    pay_scale = [
        np.maximum(np.abs(p), [SCALE_FLOOR[k_] for k_ in PAYLOAD_PARAMS]) for p in pay_nominal
    ]
    # Unconstrained weighted LS with the same unknowns: the objective's normalisation ν.
    free_gains = gain_mode != "fixed"
    known_cols: list[tuple[int, float]] = []
    if free_gains:
        for s, d in enumerate(loaded):
            assert d.run.payload is not None
            for p in np.flatnonzero(d.run.payload.known_mask()):
                known_cols.append((int(nb + 10 * s + p), float(d.run.payload.values[p])))
        if not known_cols:
            raise InputError(
                "solving the gains needs a loaded run whose payload has known parameters",
                key="--consistent-gains",
            )
    fixed_idx = np.array([c for c, _ in known_cols] + ([] if free_gains else list(range(k, k + n))))
    fixed_val = np.array([v for _, v in known_cols] + ([] if free_gains else list(gains)))
    free_idx = np.setdiff1d(np.arange(k + n), fixed_idx)
    rhs = -r[:, fixed_idx] @ fixed_val
    u_ls = np.zeros(k + n)
    u_ls[fixed_idx] = fixed_val
    u_ls[free_idx] = np.linalg.lstsq(r[:, free_idx], rhs, rcond=None)[0]
    nu_ref = float(np.sum((r @ u_ls) ** 2))
    y_sq = float(np.sum((r[:, k:] @ u_ls[k:]) ** 2))
    nu = max(nu_ref, 1e-12 * y_sq, np.finfo(float).tiny)
    rs = r / np.sqrt(nu)

    z = cp.Variable(ns)
    chi = cp.multiply(scale, z)
    parts = [bmat @ chi]
    zl = [cp.Variable(10) for _ in range(n_slots)]
    chil = [cp.multiply(pay_scale[s], zl[s]) for s in range(n_slots)]
    parts += chil
    g_var = cp.Variable(n) if free_gains else None
    parts.append(g_var if g_var is not None else gains)
    u = cp.hstack(parts)
    objective = cp.sum_squares(rs @ u)
    if prior_weight > 0.0:
        objective = objective + prior_weight * cp.sum_squares(z - chi0 / scale)
    cons = []
    bodies: list[tuple[str, cp.Expression]] = []
    for j in range(n):
        sl = inertial_slice(j)
        bodies.append((f"link{j + 1}", chi[sl]))
    for s, d in enumerate(loaded):
        assert d.run.payload is not None
        bodies.append((f"payload {d.run.payload.name}", chil[s]))
    for _, p10 in bodies:
        jv = cp.Variable((4, 4), PSD=True)
        cons.append(cp.vec(jv, order="C") == _LMAP @ p10)
    bounds = [N_PER_JOINT * j + N_INERTIAL + i for j in range(n) for i in range(len(NONNEGATIVE))]
    bounds += [N_PER_JOINT * n + i for i in range(2 * len(robot.couplings))]
    cons.append(z[bounds] >= 0)
    signs = np.sign(gains) if gain_mode == "apriori-sign" else np.ones(n)
    if g_var is not None:
        cons.append(cp.multiply(signs, g_var) >= 0)
        for c, v in known_cols:
            cons.append(u[c] == v)
    problem = cp.Problem(cp.Minimize(objective), cons)
    setup = time.perf_counter() - t_setup
    if solver not in cp.installed_solvers():
        if "SCS" not in cp.installed_solvers():
            raise IdentificationError(f"consistent fit: solver {solver} is not installed")
        solver = "SCS"  # less accurate than Clarabel: eigenvalues to about 1e-5
    opts: dict[str, float] = {"eps": 1e-9} if solver == "SCS" else {}
    try:
        problem.solve(solver=solver, **opts)
    except cp.error.SolverError as exc:
        raise IdentificationError(f"consistent fit: solver {solver} failed ({exc})") from None
    if problem.status not in ("optimal", "optimal_inaccurate") or z.value is None:
        raise IdentificationError(f"consistent fit: solver {solver} status {problem.status}")
    stats = problem.solver_stats
    solve_time = float(stats.solve_time) if stats and stats.solve_time else float("nan")

    chi_v = scale * np.asarray(z.value)
    pays = [pay_scale[s] * np.asarray(zl[s].value) for s in range(n_slots)]
    g_v = gains.copy() if g_var is None else np.asarray(g_var.value)
    theta = bmat @ chi_v
    u_v = np.concatenate([theta, *pays, g_v])
    constraints = _constraints(robot, chi_v, pays, loaded, g_v, signs, free_gains)
    quality = prediction_quality(predictions(designs, g_v, theta, pays))
    return ConsistentFit(
        standard=chi_v,
        base=theta,
        payloads=pays,
        gains=g_v,
        gain_mode=gain_mode,
        constraints=constraints,
        residual_norm=quality.residual_norm,
        relative_error=quality.relative_error,
        r2=quality.r2,
        joint_relative=quality.joint_relative,
        objective_ratio=float(np.sum((r @ u_v) ** 2) / max(nu_ref, np.finfo(float).tiny)),
        status=str(problem.status),
        solver=solver,
        solve_time_s=solve_time,
        setup_time_s=setup,
    )


def _constraints(
    robot: Robot,
    chi: np.ndarray,
    pays: Sequence[np.ndarray],
    loaded: Sequence[Design],
    gains: np.ndarray,
    signs: np.ndarray,
    free_gains: bool,
) -> list[Constraint]:
    """Every constraint's value at the solution and whether it is active."""
    out = []
    named = [(f"link{j + 1}", chi[inertial_slice(j)]) for j in range(robot.n)]
    for p, d in zip(pays, loaded, strict=True):
        assert d.run.payload is not None
        named.append((f"payload {d.run.payload.name}", p))
    for name, p10 in named:
        eig = pseudo_inertia_eigenvalues(p10)
        top = max(float(np.abs(eig).max()), np.finfo(float).tiny)
        out.append(
            Constraint(name, "pseudo_inertia", float(eig[0]), bool(eig[0] <= ACTIVE_TOL * top))
        )
    for j in range(robot.n):
        for i, kind in enumerate(NONNEGATIVE):
            v = float(chi[N_PER_JOINT * j + N_INERTIAL + i])
            floor = SCALE_FLOOR[kind]
            out.append(
                Constraint(f"{kind}{j + 1}", "nonnegative", v, bool(v <= ACTIVE_TOL * floor))
            )
    for k, c in enumerate(robot.couplings):
        for i, kind in enumerate(("fvm", "fcm")):
            v = float(chi[N_PER_JOINT * robot.n + 2 * k + i])
            out.append(
                Constraint(
                    f"{kind}{c.motor + 1}",
                    "nonnegative",
                    v,
                    bool(v <= ACTIVE_TOL * SCALE_FLOOR[kind]),
                )
            )
    if free_gains:
        for j, (g, s) in enumerate(zip(gains, signs, strict=True)):
            out.append(
                Constraint(
                    f"g{j + 1}", "gain_sign", float(g), bool(s * g <= ACTIVE_TOL * abs(g) + 1e-9)
                )
            )
    return out


def payload_estimates(fit: ConsistentFit, designs: Sequence[Design]) -> list[PayloadEstimate]:
    """The consistent payloads as :class:`PayloadEstimate` (no standard deviations: NaN)."""
    out = []
    loaded = [d for d in designs if d.loaded]
    for p, d in zip(fit.payloads, loaded, strict=True):
        assert d.run.payload is not None
        out.append(
            PayloadEstimate(
                name=d.run.payload.name,
                values=p,
                std=np.full(10, np.nan),
                nominal=d.run.payload.values.copy(),
                known=d.run.payload.known,
            )
        )
    return out


@dataclass(frozen=True)
class ConsistentCV:
    """Held-out quality of the consistent fit (same split as :mod:`.crossval`).

    Attributes
    ----------
    relative_error, r2, joint_relative
        On the held-out samples: ‖ρ‖/‖Y‖, per-joint R² and ‖ρ_j‖/‖Y_j‖.
    train_relative_error
        ‖ρ‖/‖Y‖ on the fitted samples.
    """

    relative_error: float
    r2: np.ndarray
    joint_relative: np.ndarray
    train_relative_error: float


def cross_validate_consistent(
    designs: Sequence[Design],
    bp: BaseParameters,
    robot: Robot,
    gains: np.ndarray,
    fraction: float,
    **kwargs: object,
) -> ConsistentCV:
    """Fit consistently on the first ``1 − fraction`` of every run, predict the rest.

    The row weights are those of the unconstrained fit on the same samples
    (:func:`drivegain.identify.cases.fit_case`), as in :func:`.crossval.cross_validate`.
    ``kwargs`` go to :func:`fit_consistent`.
    """
    from drivegain.identify.cases import fit_case

    train, test = split_runs(designs, fraction)
    ref = fit_case("cv", train, gains, bp.names)
    fit = fit_consistent(train, bp, robot, gains, ref.sigma_joint, **kwargs)  # type: ignore[arg-type]
    held_out = prediction_quality(predictions(test, fit.gains, fit.base, fit.payloads))
    return ConsistentCV(
        relative_error=held_out.relative_error,
        r2=held_out.r2,
        joint_relative=held_out.joint_relative,
        train_relative_error=fit.relative_error,
    )
