"""Regressor columns: which the identification keeps, and their values at given states.

The stored columns are the base columns of both coupled-wrist friction forms and the inertial
columns of the payload's link (:func:`stored_columns`); :func:`regressor_columns` evaluates
them (the standard regressor of :mod:`drivegain.dynamics.regressor` once, the other form's
coupled Coulomb columns beside it), with the Coulomb columns' sign taken of a velocity of their
own when asked (``sign_qd``, :attr:`~drivegain.identify.signal.FilterSettings.sign_cutoff_hz`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace

import numpy as np

from drivegain.config.robot import Robot, WristFriction
from drivegain.dynamics.base import BaseParameters, base_parameters, random_states
from drivegain.dynamics.model import RobotModel, build_model
from drivegain.dynamics.params import N_INERTIAL, N_PER_JOINT, standard_names
from drivegain.dynamics.regressor import stack_joint_major, standard_regressor


def column_key(name: str, form: WristFriction) -> str:
    """Key of a standard regressor column under a coupled-wrist friction form.

    Only the Coulomb columns of coupled motors (``fcmM``) differ between the forms; the stored
    regressor is that of the physical form, other forms' versions get a suffix, e.g.
    ``fcm6@paper``.
    """
    if form is not WristFriction.PHYSICAL and name.startswith("fcm"):
        return f"{name}@{form.value}"
    return name


def coupled_coulomb_columns(robot: Robot, qd: np.ndarray, form: WristFriction) -> np.ndarray:
    """Columns (N, n, couplings) of the coupled-motor Coulomb parameters under ``form``.

    Must equal the ``fcmM`` columns of :func:`standard_regressor` for that form (tested), so the
    regressor is computed once for both forms.
    """
    qd = np.atleast_2d(qd)
    out = np.zeros((qd.shape[0], robot.n, len(robot.couplings)))
    for k, c in enumerate(robot.couplings):
        s_sum = np.sign(qd[:, c.joint] + qd[:, c.motor])
        if form is WristFriction.PHYSICAL:
            out[:, c.joint, k] = s_sum
            out[:, c.motor, k] = s_sum
        else:
            s_m = np.sign(qd[:, c.motor])
            out[:, c.joint, k] = s_m
            out[:, c.motor, k] = s_sum - s_m
    return out


def _valid_for(bp: BaseParameters, model: RobotModel, form: WristFriction, seed: int) -> bool:
    """Whether ``bp`` is a base parameter set of ``model`` under friction form ``form``.

    It is when its columns reproduce the torques of random parameter vectors (the regrouping
    holds) and have full column rank (nothing is left over).
    """
    rng = np.random.default_rng(seed + 104729)
    w = stack_joint_major(standard_regressor(model, *random_states(model, 200, rng), form))
    chi = rng.standard_normal((w.shape[1], 4))
    full = w @ chi
    tol = 1e-9 * float(np.abs(full).max())
    if np.abs(w[:, bp.base_index] @ bp.regroup(chi.T).T - full).max() > tol:
        return False
    wb = w[:, bp.base_index]
    r = np.linalg.qr(wb / np.linalg.norm(wb, axis=0), mode="r")
    d = np.abs(np.diag(r))
    return bool(d.min() > 1e-8 * d.max())


def bases_for_forms(model: RobotModel, *, seed: int = 0) -> dict[WristFriction, BaseParameters]:
    """Base parameters of ``model`` under every coupled-wrist friction form.

    The set found for the robot's own form is reused for another form when it is valid there
    too (only the coupled Coulomb column changes), which halves the cost.
    """
    own = model.robot.wrist_friction
    first = base_parameters(model, seed=seed)
    out = {own: first}
    for form in WristFriction:
        if form is own:
            continue
        if _valid_for(first, model, form, seed):
            out[form] = first
        else:
            other = build_model(replace(model.robot, wrist_friction=form))
            out[form] = base_parameters(other, seed=seed)
    return out


def base_keys(bp: BaseParameters, form: WristFriction) -> list[str]:
    """Column keys of the base parameters of ``bp`` (computed for ``form``)."""
    return [column_key(bp.standard_names[k], form) for k in bp.base_index]


def payload_keys(robot: Robot, link: int) -> list[str]:
    """Column keys of the 10 inertial parameters of ``link`` (1-based), payload order."""
    names = standard_names(robot)
    start = N_PER_JOINT * (link - 1)
    return names[start : start + N_INERTIAL]


def stored_columns(
    robot: Robot, bases: Mapping[WristFriction, BaseParameters], payload_links: Iterable[int]
) -> tuple[str, ...]:
    """The regressor columns to keep: base columns of every form and payload-link columns."""
    names = standard_names(robot)
    keep: set[str] = set()
    for form, bp in bases.items():
        keep.update(base_keys(bp, form))
    for link in payload_links:
        keep.update(payload_keys(robot, link))
    ordered = [nm for nm in names if nm in keep]
    extra = sorted(k for k in keep if k not in names)
    return (*ordered, *extra)


def _sources(robot: Robot, columns: Sequence[str]) -> tuple[np.ndarray, list[tuple[int, str, int]]]:
    """Where each stored column comes from: standard indices (−1 for another form's column)
    and, for those, (position, form, coupling index)."""
    names = standard_names(robot)
    fcm_names = [f"fcm{c.motor + 1}" for c in robot.couplings]
    std = np.full(len(columns), -1, dtype=int)
    alt = []
    for i, key in enumerate(columns):
        name, _, form = key.partition("@")
        if form:
            alt.append((i, form, fcm_names.index(name)))
        else:
            std[i] = names.index(name)
    return std, alt


def _coulomb_column(robot: Robot, key: str, qd: np.ndarray) -> np.ndarray | None:
    """Column ``key`` (N, n) of the regressor when it is a Coulomb column (``FcJ``, ``fcmM``
    of any form), computed from the velocities ``qd``; None for any other column."""
    name, _, form = key.partition("@")
    if name.startswith("Fc") and name[2:].isdigit():
        j = int(name[2:]) - 1
        out = np.zeros((qd.shape[0], robot.n))
        out[:, j] = np.sign(qd[:, j])
        return out
    if name.startswith("fcm"):
        motors = [f"fcm{c.motor + 1}" for c in robot.couplings]
        cc = coupled_coulomb_columns(robot, qd, WristFriction(form or WristFriction.PHYSICAL))
        return cc[:, :, motors.index(name)]
    return None


def regressor_columns(
    model: RobotModel,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    columns: Sequence[str],
    series: tuple[np.ndarray, np.ndarray] | None = None,
    sign_qd: np.ndarray | None = None,
) -> np.ndarray:
    """The regressor restricted to ``columns`` (keys of :func:`stored_columns`).

    Returns (N, n, c); or, with ``series = (rows, cols)`` index arrays, only those entries,
    (N, len(rows)). ``sign_qd`` (N, n), rad/s: the velocities whose signs the Coulomb columns
    take (:attr:`~drivegain.identify.signal.FilterSettings.sign_cutoff_hz`); None: ``qd``.
    """
    robot = model.robot
    std, alt = _sources(robot, columns)
    w = standard_regressor(model, q, qd, qdd, WristFriction.PHYSICAL)
    src = np.where(std >= 0, std, 0)
    vs = np.atleast_2d(qd if sign_qd is None else sign_qd)
    # Columns not taken from w: the other forms' coupled Coulomb columns, and with a sign
    # velocity of their own the Coulomb columns w took of qd. All are signs of vs.
    extra: dict[int, np.ndarray] = {}
    by_form: dict[str, np.ndarray] = {}
    for i, form, k in alt:
        if form not in by_form:
            by_form[form] = coupled_coulomb_columns(robot, vs, WristFriction(form))
        extra[i] = by_form[form][:, :, k]
    if sign_qd is not None:
        for i, key in enumerate(columns):
            if i not in extra and (col := _coulomb_column(robot, key, vs)) is not None:
                extra[i] = col
    if series is None:
        out = w[:, :, src]
        for i, col in extra.items():
            out[:, :, i] = col
        return np.asarray(out)
    rows, cols = series
    out = w[:, rows, src[cols]]
    for i, col in extra.items():
        sel = np.flatnonzero(cols == i)
        out[:, sel] = col[:, rows[sel]]
    return np.asarray(out)
