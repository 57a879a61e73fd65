"""The simulated robot behind the mocked bus: forward dynamics and the drives' control loops.

One instance holds the whole arm (the drives of a coupled wrist share dynamics). Dynamics use the
true standard parameters ``chi`` (:mod:`drivegain.dynamics.params`): Pinocchio's CRBA and
nonlinear effects on bodies built from ``chi``, plus rotor inertia, friction (the wrist form of the
robot or of the simulation config), torque offsets and the coupled motor's terms, exactly as
:func:`drivegain.dynamics.regressor.standard_regressor` models them (a test checks
``M(q) qdd + h(q, qd) == standard_regressor(q, qd, qdd) @ chi``).

Each drive runs a cascaded controller on its motor at the internal step ``dt``: CSP setpoint
interpolated linearly over one SYNC period with velocity feed-forward, proportional position loop,
PI velocity loop on the velocity differentiated from quantised encoder counts, current limit. The
motor torque is (true gain / gear ratio) × (current reference + current-loop noise); joint torques
are ``K.T @ motor torques`` (``tau = V(i) g``, eq. 21). A motor whose drive is not powered is held
by its brake (its motor coordinate is locked; braking is instantaneous).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace
from enum import IntEnum
from typing import Any

import numpy as np
import pinocchio as pin

from drivegain.config.payload import Payload
from drivegain.config.robot import Robot, WristFriction
from drivegain.config.truth import Truth
from drivegain.dynamics.model import build_model
from drivegain.dynamics.params import (
    N_PER_JOINT,
    inertial_slice,
    to_pinocchio_order,
    truth_vector,
    with_payload,
)

#: Internal steps of motor state kept for :meth:`RobotPhysics.motor_state_at` (32 ms at 0.5 ms).
RECENT_STEPS = 64
#: Rows of current-loop noise drawn at once: one draw per step would cost more than the step's
#: arithmetic, and the generator releases the interpreter lock on every call (another thread
#: then holds it). A block is the same sequence of numbers as one draw of n per step.
NOISE_BLOCK = 1024


try:  # the gufunc behind np.linalg.solve for one right-hand side
    from numpy.linalg import _umath_linalg

    _SOLVE1: Any = _umath_linalg.solve1
except (ImportError, AttributeError):  # pragma: no cover - another numpy layout
    _SOLVE1 = None


def _solve(m: np.ndarray, f: np.ndarray) -> np.ndarray:
    """``np.linalg.solve(m, f)`` for a vector ``f``: the same LAPACK routine, without the
    wrapper's per-call set-up (it dominates at n = 6); a singular ``m`` goes to the wrapper,
    which raises."""
    if _SOLVE1 is None:
        return np.linalg.solve(m, f)
    x: np.ndarray = _SOLVE1(m, f, signature="dd->d")
    if not np.isfinite(x).all():
        return np.linalg.solve(m, f)
    return x


class MotorMode(IntEnum):
    """What drives a motor during a step."""

    BRAKED = 0  # power off, brake holds the motor
    TRACK = 1  # position loop on the CSP setpoint
    QUICK_STOP = 2  # position loop on a deceleration ramp to rest


@dataclass(frozen=True)
class LoopGains:
    """Per-motor controller gains (motor side).

    kp: position loop, 1/s; kv: velocity loop, A per (rad/s); ki: velocity integral, A per rad;
    i_max: current limit, A.
    """

    kp: np.ndarray
    kv: np.ndarray
    ki: np.ndarray
    i_max: np.ndarray


@dataclass(slots=True)  # not frozen: made at every internal step, frozen ones cost more
class StepOutput:
    """What the drives apply during one internal step and the resulting acceleration.

    All (n,) arrays. ``setpoint`` and ``following_error`` are motor side (rad); ``tau`` and
    ``qdd`` joint side (N·m, rad/s²); currents in A.
    """

    setpoint: np.ndarray
    following_error: np.ndarray
    current_reference: np.ndarray
    current: np.ndarray
    tau: np.ndarray
    qdd: np.ndarray


def truth_parameters(robot: Robot, truth: Truth, payload: Payload | None = None) -> np.ndarray:
    """The standard parameter vector of the simulated robot (payload on its link if given)."""
    chi = truth_vector(robot, truth)
    if payload is not None:
        chi = with_payload(robot, chi, payload)
    return chi


def _sign(x: float) -> float:
    """``np.sign`` of a float (0 at 0, NaN for NaN)."""
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return x * 0.0 if x != x else 0.0


class Dynamics:
    """Inverse/forward dynamics of the true robot from its standard parameters.

    Parameters
    ----------
    robot
        The robot description (kinematics, couplings).
    chi
        Standard parameters (see :mod:`drivegain.dynamics.params`).
    friction
        Friction form of the coupled motors; default the robot file's.
    """

    def __init__(self, robot: Robot, chi: np.ndarray, friction: WristFriction | str | None = None):
        self.robot = robot
        self.n = n = robot.n
        self.form = WristFriction(friction or robot.wrist_friction)
        self.model = build_model(robot).pin_model.copy()
        for j in range(n):
            self.model.inertias[j + 1] = pin.Inertia.FromDynamicParameters(
                to_pinocchio_order(chi[inertial_slice(j)])
            )
        self.data = self.model.createData()
        probe = pin.crba(self.model, self.data, np.linspace(0.3, 1.3, n))
        # Some Pinocchio versions fill only the upper triangle.
        self._symmetrize = not np.allclose(np.tril(probe, -1), np.triu(probe, 1).T)
        per_joint = chi[: N_PER_JOINT * n].reshape(n, N_PER_JOINT)
        self.ia, self.fv, self.fc, self.offset = (per_joint[:, k].copy() for k in (10, 11, 12, 13))
        self.rotor = np.diag(self.ia)
        self.couplings: list[tuple[int, int, float, float]] = []
        for k, c in enumerate(robot.couplings):
            ia_m = self.ia[c.motor]
            self.rotor[c.joint, c.motor] += ia_m
            self.rotor[c.motor, c.joint] += ia_m
            fvm, fcm = chi[N_PER_JOINT * n + 2 * k : N_PER_JOINT * n + 2 * k + 2]
            self.couplings.append((c.motor, c.joint, float(fvm), float(fcm)))

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """Joint-space inertia matrix incl. rotor inertia (n, n), kg·m²."""
        m = pin.crba(self.model, self.data, q)
        if self._symmetrize:
            m = np.triu(m) + np.triu(m, 1).T
        return m + self.rotor

    def bias(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Coriolis, centrifugal, gravity, friction and offset torques (n,), N·m."""
        h = pin.nle(self.model, self.data, q, qd) + self.fv * qd + self.fc * np.sign(qd)
        h = h + self.offset
        if not self.couplings:
            return h
        # Python floats: the same IEEE operations as numpy's scalars, without their overhead
        v = qd.tolist()
        hl = h.tolist()
        for m, o, fvm, fcm in self.couplings:
            s_sum = _sign(v[o] + v[m])
            hl[o] += fvm * v[m]
            hl[m] += fvm * v[o]
            if self.form is WristFriction.PHYSICAL:
                hl[o] += fcm * s_sum
                hl[m] += fcm * s_sum
            else:  # eq. (22) as printed
                s_m = _sign(v[m])
                hl[o] += fcm * s_m
                hl[m] += fcm * (s_sum - s_m)
        return np.array(hl)

    def inverse(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """Joint torques (n,) that produce ``qdd`` at (q, qd)."""
        return self.mass_matrix(q) @ qdd + self.bias(q, qd)


def design_gains(
    robot: Robot,
    dyn: Dynamics,
    gains: np.ndarray,
    q0: np.ndarray,
    *,
    bandwidth_hz: float = 60.0,
    current_limit: float = 3.0,
) -> LoopGains:
    """Controller gains of every drive, tuned on the inertia each motor sees at pose ``q0``.

    The velocity loop has crossover ``bandwidth_hz`` (kv = ω·J_m/Kt with the motor-side inertia
    J_m and torque constant Kt = gain / gear ratio), the integral corner at ω/6 and the position
    loop at ω/4 (a well-damped cascade). ``current_limit`` is in multiples of the rated current.
    """
    k = robot.transmission()
    kinv = np.linalg.inv(k)
    m_motor = kinv.T @ dyn.mass_matrix(np.asarray(q0, float)) @ kinv
    kt = np.asarray(gains, float) / robot.gear_ratios
    omega = 2.0 * np.pi * bandwidth_hz
    kv = omega * np.diag(m_motor) / kt
    rated = np.array([j.rated_current for j in robot.joints])
    return LoopGains(
        kp=np.full(robot.n, omega / 4.0),
        kv=kv,
        ki=kv * omega / 6.0,
        i_max=current_limit * rated,
    )


class RobotPhysics:
    """State and time integration of the simulated arm with its drives.

    Parameters
    ----------
    robot
        Robot description.
    dynamics
        The true dynamics.
    gains
        True drive gains (N·m/A, joint side).
    loop
        Controller gains.
    dt
        Internal integration step, s.
    q0
        Initial joint positions, rad.
    noise_nm
        Standard deviation of the current-loop error of each drive, expressed as joint torque
        of that drive (N·m).
    rng
        Random generator for the noise.
    """

    def __init__(
        self,
        robot: Robot,
        dynamics: Dynamics,
        gains: np.ndarray,
        loop: LoopGains,
        dt: float,
        q0: np.ndarray,
        noise_nm: float,
        rng: np.random.Generator,
    ):
        self.robot = robot
        self.dyn = dynamics
        self.n = robot.n
        self.dt = dt
        self.k = robot.transmission()
        self.kinv = np.linalg.inv(self.k)
        self.gains = np.asarray(gains, float)
        self.ratios = robot.gear_ratios
        self.kt = self.gains / self.ratios
        self.loop = loop
        self.cpr = np.array([j.encoder_counts for j in robot.joints], dtype=float) / (2 * np.pi)
        self.noise_std = noise_nm / np.abs(self.gains)
        self.rng = rng
        self._noise_rows = np.zeros((0, self.n))
        self._zeros = np.zeros(self.n)
        self._zeros.flags.writeable = False
        self._noise_at = 0
        self._kt_t = np.ascontiguousarray(self.k.T)
        self._neg_i_max = -np.asarray(loop.i_max, float)
        self.q = np.array(q0, dtype=float)
        self.qd = np.zeros(self.n)
        self.step_index = 0
        self.modes = np.zeros(self.n, dtype=int)
        # Setpoint generator (motor side): linear interpolation from `_from` to `_to` over
        # `_span` seconds starting at `_t_latch`; quick stop: ramp velocity `_qs_v` to 0.
        xm = self.motor_positions()
        self._from = xm.copy()
        self._to = xm.copy()
        self._t_latch = np.zeros(self.n)
        self._span = np.full(self.n, 1.0)
        self._interpolation_changed()
        self._qs_v = np.zeros(self.n)
        self._qs_pos = xm.copy()
        self._qs_decel = np.full(self.n, np.inf)
        self._integral = np.zeros(self.n)
        self._i_sum = np.zeros(self.n)
        self._tau_sum = np.zeros(self.n)
        self._i_steps = 0
        self._prev_meas = self._measured()
        self._pending: StepOutput | None = None
        self._pending_accel = False  # the cached outputs include the acceleration
        self._nan = np.full(self.n, np.nan)
        self._nan.flags.writeable = False
        self._pending_loop: tuple[np.ndarray, np.ndarray] = (np.zeros(self.n), self._prev_meas)
        # Motor angles and speeds at the start of the last steps, by step index: what a drive
        # latched at a SYNC that the realtime integrator has already run past (kept only after
        # keep_recent_steps: lockstep never needs them).
        self._recent: deque[tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=0)
        self._update_masks()

    # --- observation ------------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        return self.step_index * self.dt

    def motor_positions(self) -> np.ndarray:
        """Motor angles K q, rad."""
        return self.k @ self.q

    def motor_velocities(self) -> np.ndarray:
        return self.k @ self.qd

    def keep_recent_steps(self, steps: int = RECENT_STEPS) -> None:
        """Keep the motor state of the last ``steps`` internal steps for :meth:`motor_state_at`."""
        self._recent = deque(self._recent, maxlen=steps)

    def motor_state_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Motor angles (rad) and speeds (rad/s) at simulated time ``t`` (s, at most now).

        Interpolated linearly between the internal steps kept (see :meth:`keep_recent_steps`);
        the present state for ``t`` now or later, the oldest kept for anything older.
        """
        recent = self._recent
        if t >= self.time_s or not recent:
            return self.motor_positions(), self.motor_velocities()
        x = t / self.dt
        later = (self.step_index, self.motor_positions(), self.motor_velocities())
        for entry in reversed(recent):
            if entry[0] <= x:
                w = (x - entry[0]) / (later[0] - entry[0])
                return (
                    entry[1] + w * (later[1] - entry[1]),
                    entry[2] + w * (later[2] - entry[2]),
                )
            later = entry
        return recent[0][1], recent[0][2]

    def encoder_counts(self) -> np.ndarray:
        """Encoder readings (counts, int64) of every motor."""
        return np.rint(self.motor_positions() * self.cpr).astype(np.int64)

    def _measured(self) -> np.ndarray:
        return np.rint(self.k @ self.q * self.cpr) / self.cpr

    @property
    def any_powered(self) -> bool:
        """Some motor is driven (otherwise integration is trivial)."""
        return self._any_powered

    @property
    def any_quick_stop(self) -> bool:
        """Some motor is on its quick stop ramp."""
        return self._any_qs

    def quick_stop_done(self) -> np.ndarray:
        """Motors in QUICK_STOP whose ramp has reached rest."""
        return self._qs & (self._qs_v == 0.0)

    # --- commands ---------------------------------------------------------------------------
    def set_mode(self, motor: int, mode: MotorMode) -> None:
        """Change what drives ``motor``; entering TRACK starts from the measured position."""
        old = self.modes[motor]
        if old == mode:
            return
        meas = self._measured()[motor]
        if mode == MotorMode.TRACK:
            self._from[motor] = self._to[motor] = meas
            self._interpolation_changed()
            self._integral[motor] = 0.0
            if old == MotorMode.BRAKED:
                self._prev_meas[motor] = meas
        elif mode == MotorMode.QUICK_STOP:
            self._qs_v[motor] = self.motor_velocities()[motor]
            self._qs_pos[motor] = self._setpoint_at(self.time_s)[0][motor]
        else:
            self._integral[motor] = 0.0
            # The brake stops the motor at once.
            xd = self.k @ self.qd
            xd[motor] = 0.0
            self.qd = self.kinv @ xd
        self.modes[motor] = int(mode)
        self._update_masks()

    def _update_masks(self) -> None:
        # Plain arrays and bools: enum comparisons are slow in the integration loop.
        self._powered = self.modes != int(MotorMode.BRAKED)
        self._braked = ~self._powered
        self._qs = self.modes == int(MotorMode.QUICK_STOP)
        self._any_powered = bool(self._powered.any())
        self._all_powered = bool(self._powered.all())
        self._any_qs = bool(self._qs.any())
        self._pending = None

    def set_quick_stop_deceleration(self, decel: np.ndarray) -> None:
        """Quick stop ramp of every motor, rad/s² (motor side)."""
        self._qs_decel = np.asarray(decel, float).copy()

    def latch_targets(self, targets: np.ndarray, mask: np.ndarray, period_s: float) -> None:
        """New CSP targets (motor rad) for the motors in ``mask``: the setpoint moves linearly
        from where it is now to the target over ``period_s``."""
        if not np.any(mask):
            return
        now = self.time_s
        current, _ = self._setpoint_at(now)
        self._from = np.where(mask, current, self._from)
        self._to = np.where(mask, targets, self._to)
        self._t_latch = np.where(mask, now, self._t_latch)
        self._span = np.where(mask, period_s, self._span)
        self._interpolation_changed()
        self._pending = None

    def _interpolation_changed(self) -> None:
        """Derive what :meth:`_setpoint_at` reads from ``_from``, ``_to``, ``_t_latch`` and
        ``_span``, after any of them changed."""
        self._diff = self._to - self._from
        self._slope = self._diff / self._span  # setpoint speed while interpolating
        # every motor latched at one instant over one span: the scalar path
        self._uniform = bool(
            (self._t_latch == self._t_latch[0]).all() and (self._span == self._span[0]).all()
        )

    # --- evaluation and integration ---------------------------------------------------------
    def _setpoint_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        if self._uniform:
            # one fraction for every motor: the same float operations as the vector path
            f = (t - float(self._t_latch[0])) / float(self._span[0])
            f = min(max(f, 0.0), 1.0)
            return self._from + self._diff * f, (self._slope if f < 1.0 else self._zeros)
        # np.minimum/np.maximum: np.clip's values without its wrapper's cost
        frac = np.minimum(np.maximum((t - self._t_latch) / self._span, 0.0), 1.0)
        pos = self._from + self._diff * frac
        vel = np.where(frac < 1.0, self._slope, 0.0)
        return pos, vel

    def _noise(self) -> np.ndarray:
        """The next row of standard normal current-loop noise, (n,)."""
        at = self._noise_at
        if at == len(self._noise_rows):
            self._noise_rows = self.rng.standard_normal((NOISE_BLOCK, self.n))
            at = 0
        self._noise_at = at + 1
        return self._noise_rows[at]

    def evaluate(self, accel: bool = True) -> StepOutput:
        """Controller outputs and acceleration for the step starting now (cached until the
        state or a command changes).

        ``accel=False``: the controller outputs only, ``qdd`` left NaN (no forward dynamics,
        the costliest part); a later call with ``accel`` completes the cached outputs with the
        acceleration, the same as if it had been computed at once.
        """
        pending = self._pending
        if pending is not None:
            if not accel or self._pending_accel:
                return pending
            out = replace(pending, qdd=self._accel(pending.tau))
            self._pending = out
            self._pending_accel = True
            return out
        sp, v_ff = self._setpoint_at(self.time_s)
        if self._any_qs:
            sp = np.where(self._qs, self._qs_pos, sp)
            v_ff = np.where(self._qs, self._qs_v, v_ff)
        meas = self._measured()
        vel = (meas - self._prev_meas) / self.dt
        powered = self._powered
        loop = self.loop
        err = sp - meas
        ev = loop.kp * err + v_ff - vel
        i_ref = loop.kv * ev + self._integral
        i_ref = np.minimum(np.maximum(i_ref, self._neg_i_max), loop.i_max)
        noise = self._noise() * self.noise_std
        if self._all_powered:  # np.where(powered, x, 0) is x: skip the copies
            i_act = i_ref + noise
            following_error = err
        else:
            i_ref = np.where(powered, i_ref, 0.0)
            i_act = np.where(powered, i_ref + noise, 0.0)
            following_error = np.where(powered, err, 0.0)
        tau = self._kt_t @ (self.kt * i_act)
        qdd = self._accel(tau) if accel else self._nan
        out = StepOutput(
            setpoint=sp,
            following_error=following_error,
            current_reference=i_ref,
            current=i_act,
            tau=tau,
            qdd=qdd,
        )
        self._pending = out
        self._pending_accel = accel
        self._pending_loop = (ev, meas)
        return out

    def _accel(self, tau: np.ndarray) -> np.ndarray:
        """Joint accelerations (rad/s²) under the motor torques ``tau`` in the present state."""
        return self._forward(tau) if self._any_powered else np.zeros(self.n)

    def _forward(self, tau: np.ndarray) -> np.ndarray:
        m = self.dyn.mass_matrix(self.q)
        f = tau - self.dyn.bias(self.q, self.qd)
        if self._all_powered:
            return _solve(m, f)
        # Locked motor coordinates: solve in x = K q on the free ones only.
        free = self._powered
        m_motor = self.kinv.T @ m @ self.kinv
        f_motor = self.kinv.T @ f
        xdd = np.zeros(self.n)
        xdd[free] = np.linalg.solve(m_motor[np.ix_(free, free)], f_motor[free])
        return self.kinv @ xdd

    def take_period_means(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean current reference (A) and mean applied joint torque (N·m) over the steps
        integrated since the last call (the last SYNC period).

        Drives report a torque demand averaged over their reporting period: a point sample of
        the fast current loop (velocity from encoder differences every step) would alias its
        ripple into the identification band.
        """
        if self._i_steps == 0:
            out = self.evaluate()
            return out.current_reference.copy(), out.tau.copy()
        means = (self._i_sum / self._i_steps, self._tau_sum / self._i_steps)
        self._i_sum = np.zeros(self.n)
        self._tau_sum = np.zeros(self.n)
        self._i_steps = 0
        return means

    def advance(self, steps: int) -> None:
        """Integrate ``steps`` internal steps (semi-implicit Euler)."""
        remaining = max(0, steps)
        while remaining > 0:
            powered = self._powered
            if not self._any_powered:
                # Everything braked: nothing moves, skip the remaining steps at once.
                self.qd[:] = 0.0
                self.step_index += remaining
                self._prev_meas = self._measured()
                self._pending = None
                self._recent.clear()  # nothing moved: the present state is every recent one
                return
            if self._recent.maxlen:
                self._recent.append((self.step_index, self.k @ self.q, self.k @ self.qd))
            out = self.evaluate()
            ev, meas = self._pending_loop
            # Conditional integration: the integral holds while the current saturates.
            saturated = np.abs(out.current_reference) >= self.loop.i_max
            grown = self._integral + self.loop.ki * ev * self.dt
            held = np.where(saturated, self._integral, grown)
            self._integral = held if self._all_powered else np.where(powered, held, 0.0)
            self._prev_meas = meas
            self._i_sum += out.current_reference
            self._tau_sum += out.tau
            self._i_steps += 1
            self.qd = self.qd + out.qdd * self.dt
            if not self._all_powered:
                xd = self.k @ self.qd
                xd[self._braked] = 0.0
                self.qd = self.kinv @ xd
            self.q = self.q + self.qd * self.dt
            if self._any_qs:
                qs = self._qs
                v = self._qs_v
                new_v = v - np.sign(v) * np.minimum(np.abs(v), self._qs_decel * self.dt)
                self._qs_pos = np.where(
                    qs, self._qs_pos + 0.5 * (v + new_v) * self.dt, self._qs_pos
                )
                self._qs_v = np.where(qs, new_v, self._qs_v)
            self.step_index += 1
            self._pending = None
            remaining -= 1
