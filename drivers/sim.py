"""The simulated robot cell: one simulated CiA 402 drive per joint on a (virtual) CAN channel,
all behind one shared physics simulation.

The cell opens its own bus and :class:`canopen.Network` on the configured channel (python-can's
virtual bus delivers frames between buses of the same channel, never to their sender), so the
master side is exactly the code that runs on hardware. Time:

- ``lockstep``: every SYNC advances the physics by exactly one period (deterministic, as fast as
  the machine allows); heartbeats, the heartbeat consumers and late TPDOs run on the simulated
  clock shared with the master (:mod:`.simtime`, on the in-process ``virtual`` bus, which then
  hands frames over in the sender's thread; drives in a process of their own keep the wall clock);
- ``realtime``: the physics follows the wall clock since :meth:`start` (an integrator thread
  between SYNCs); a SYNC is handled at the instant the bus stamped it with.

At each SYNC the cell integrates up to the SYNC instant, triggers due faults and sends the TPDOs
first, with what the drives sampled at that instant (position, current, the current reference
averaged over the period just ended, statusword), as a drive that answers the SYNC before its
control update. Then each drive applies the RPDO data received before the SYNC (controlword, CSP
target), the control loops are evaluated and the truth is recorded
(:meth:`joint_torque_history`). A controlword's effect therefore shows in the next SYNC's
statusword. In ``realtime`` the cell then computes the motion up to the next SYNC expected, so
that the drives' answer to it waits for no physics.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np

from drivegain.config import load_payload, load_truth
from drivegain.config.robot import Robot, WristFriction
from drivegain.drivers import objects as ob
from drivegain.drivers.bus import BusConfig, open_network
from drivegain.drivers.clock import Clock
from drivegain.drivers.faults import FaultKind, FaultSpec
from drivegain.drivers.physics import Dynamics, RobotPhysics, design_gains, truth_parameters
from drivegain.drivers.simclock import CellClock, Integrator
from drivegain.drivers.simconfig import SimConfig
from drivegain.drivers.simdrive import NmtState, SimDrive
from drivegain.drivers.simtime import LockstepClock
from drivegain.errors import ConfigError, DriveError
from drivegain.lifecycle import Running, release_quietly

logger = logging.getLogger(__name__)

#: Following error window of the simulated drives, joint side (rad), and its time-out (ms).
FOLLOWING_ERROR_WINDOW_RAD = 0.1
FOLLOWING_ERROR_TIMEOUT_MS = 20
#: Quick stop deceleration, in multiples of the joint's acceleration limit.
QUICK_STOP_FACTOR = 4.0
#: Objects the simulated drive reads or writes besides its commissioned ones.
SIM_REQUIRED_OBJECTS = frozenset(
    {
        ob.DEVICE_TYPE,
        ob.PRODUCER_HEARTBEAT,
        ob.CONTROLWORD,
        ob.STATUSWORD,
        ob.MODES_OF_OPERATION,
        ob.MODES_DISPLAY,
        ob.POSITION_ACTUAL,
        ob.TARGET_POSITION,
    }
)
#: Largest velocity-loop crossover times internal step (rad) that stays well damped.
MAX_LOOP_PHASE = 0.4
#: socketcan error class bit for bus-off, as python-can reports it in ``arbitration_id``.
CAN_ERR_BUSOFF = 0x40


@dataclass(frozen=True)
class SimHistory:
    """The simulated truth at every SYNC (N samples; (N, n) arrays, joint side).

    ``tau`` are the joint torques the motors applied (N·m), ``current_reference`` and
    ``current`` the drives' currents (A, before the per-mille quantisation of the TPDOs),
    ``setpoint`` the drives' interpolated setpoints mapped to the joints (rad), all at the SYNC
    instant. ``current_reference_mean`` and ``tau_mean`` are averages over the SYNC period that
    ends at the sample: what the drives report as torque demand, and the torque it produced.
    """

    sync_index: np.ndarray
    counter: np.ndarray
    time_s: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau: np.ndarray
    current_reference: np.ndarray
    current: np.ndarray
    setpoint: np.ndarray
    current_reference_mean: np.ndarray
    tau_mean: np.ndarray

    def __len__(self) -> int:
        return len(self.sync_index)


@dataclass(frozen=True)
class FaultRecord:
    """When an injected fault took effect: simulated seconds since the first SYNC, and the
    cell's clock (lockstep's simulated clock, else ``time.monotonic()``), s."""

    spec: FaultSpec
    sim_time_s: float
    clock_s: float


#: Buses on which the drives in this process share the master's lockstep clock.
LOCKSTEP_INTERFACES = ("virtual", "socketcan")


class SimulatedCell(Running):
    """Simulated drives (canopen LocalNodes) and robot physics on a CAN channel.

    Parameters
    ----------
    robot
        The robot (joints, node ids, encoders, couplings).
    bus_cfg
        The bus to attach to (normally ``interface = "virtual"``).
    sim
        Simulation settings.
    period_s
        SYNC period the master will use, s (sets the internal step and the CSP interpolation).
    eds
        EDS of the simulated drives; default the shipped ``cia402-servo.eds``.
    """

    def __init__(
        self,
        robot: Robot,
        bus_cfg: BusConfig,
        sim: SimConfig,
        period_s: float,
        *,
        eds: Path | None = None,
    ):
        if period_s <= 0.0:
            raise ConfigError(f"the SYNC period must be > 0 s, got {period_s}")
        self.robot = robot
        self.bus_cfg = bus_cfg
        self.sim = sim
        self.period_s = period_s
        self.eds = eds or ob.default_eds()
        self.truth = load_truth(sim.truth, n_links=robot.n)
        self.payload = load_payload(sim.payload, n_links=robot.n) if sim.payload else None
        node_ids = set(robot.node_ids)
        for spec in sim.faults:
            if spec.node is not None and spec.node not in node_ids:
                raise ConfigError(f"fault {spec.kind}: no joint has node id {spec.node}")
        q0 = np.zeros(robot.n) if sim.initial_position is None else np.array(sim.initial_position)
        if q0.shape != (robot.n,):
            raise ConfigError(f"initial_position needs {robot.n} values, got {q0.size}")
        if np.any(q0 < robot.lower) or np.any(q0 > robot.upper):
            raise ConfigError("initial_position is outside the joint limits")
        self.substeps = max(2, math.ceil(period_s / sim.max_step_s - 1e-9))
        self.dt = period_s / self.substeps
        if 2.0 * math.pi * sim.bandwidth_hz * self.dt > MAX_LOOP_PHASE:
            raise ConfigError(
                f"velocity loop bandwidth {sim.bandwidth_hz} Hz is too high for the internal "
                f"step of {self.dt * 1e3:.3f} ms: lower bandwidth_hz or max_step_s"
            )
        chi = truth_parameters(robot, self.truth, self.payload)
        friction = WristFriction(sim.friction) if sim.friction else None
        self.dynamics = Dynamics(robot, chi, friction)
        loop = design_gains(
            robot, self.dynamics, self.truth.gains, q0, bandwidth_hz=sim.bandwidth_hz
        )
        self.physics = RobotPhysics(
            robot,
            self.dynamics,
            self.truth.gains,
            loop,
            self.dt,
            q0,
            sim.current_noise_nm,
            np.random.default_rng(sim.seed),
        )
        ratios = np.abs(robot.gear_ratios)
        self.physics.set_quick_stop_deceleration(
            QUICK_STOP_FACTOR * robot.acceleration_limits * ratios
        )
        self._cpr = np.array([j.encoder_counts for j in robot.joints]) / (2.0 * math.pi)
        # lockstep shares its simulated clock with the master: only within one process, on a
        # bus that hands every frame of one side to the other (python-can's virtual bus, or a
        # kernel socketcan device such as vcan0: its stamps are wall time, read as "now")
        shared = sim.clock == Clock.LOCKSTEP and bus_cfg.interface in LOCKSTEP_INTERFACES
        self.clock = CellClock(self.guard, LockstepClock() if shared else None)
        self.drives: dict[int, SimDrive] = {}
        for j, joint in enumerate(robot.joints):
            od = ob.load_od(self.eds, joint.node_id)
            kt = abs(self.truth.gains[j] / joint.gear_ratio)
            window = FOLLOWING_ERROR_WINDOW_RAD * ratios[j] * self._cpr[j]
            decel = QUICK_STOP_FACTOR * joint.acceleration_limit * ratios[j] * self._cpr[j]
            commissioning = {
                (ob.RATED_CURRENT, 0): round(joint.rated_current * 1000),
                (ob.RATED_TORQUE, 0): round(kt * joint.rated_current * 1000),
                (ob.ENCODER_RESOLUTION, 1): joint.encoder_counts,
                (ob.ENCODER_RESOLUTION, 2): 1,
                (ob.FOLLOWING_ERROR_WINDOW, 0): round(window),
                (ob.FOLLOWING_ERROR_TIMEOUT, 0): FOLLOWING_ERROR_TIMEOUT_MS,
                (ob.QUICK_STOP_DECELERATION, 0): min(round(decel), 0x7FFFFFFF),
            }
            missing = [
                f"0x{index:04X}"
                for index in sorted({i for i, _ in commissioning} | SIM_REQUIRED_OBJECTS)
                if index not in od
            ]
            if missing:
                raise ConfigError(
                    f"the EDS lacks objects the simulated drive needs: {', '.join(missing)}",
                    file=self.eds,
                )
            drive = SimDrive(self, j, joint.node_id, od, commissioning)
            if any(s.kind == FaultKind.NEVER_BOOTS and s.node == joint.node_id for s in sim.faults):
                drive.never_boots = True
            self.drives[joint.node_id] = drive
        self._network: canopen.Network | None = None
        self._watched: set[int] = set()  # heartbeat producers some consumer listens to
        self._ramp_watch = False
        self._t0 = 0.0
        self._sync_index = 0
        self._t_first: float | None = None
        self._pending_faults = [s for s in sim.faults if s.kind != FaultKind.NEVER_BOOTS]
        self._fault_log: list[FaultRecord] = []
        self._errors: deque[str] = deque(maxlen=100)
        self._history: deque[tuple[Any, ...]] = deque(
            maxlen=max(1, round(sim.history_s / period_s))
        )
        self._lock = threading.Lock()  # history and fault log, read from other threads
        # Physics and drive state: bus callbacks, timer actions and the realtime integrator.
        self._physics_lock = threading.RLock()
        self._integrator: Integrator | None = None
        if sim.clock == Clock.REALTIME:
            self.physics.keep_recent_steps()
        self._publish_samples()

    # --- lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        """Attach to the bus and power the drives on (boot-up messages)."""
        if self._network is not None:
            raise DriveError("the simulated cell is already started")
        self._network = open_network(self.bus_cfg)
        try:
            for drive in self.drives.values():
                self._network.add_node(drive.node)
            self._network.subscribe(0x80, self._on_sync)
            if self.clock.lockstep is not None:  # after canopen's listener: counts handled frames
                self.clock.lockstep.attach(self._network, "drives")
            self.clock.start()
            self._t0 = time.monotonic()
            if self.sim.clock == Clock.REALTIME:
                self._integrator = Integrator(self)
                self._integrator.start()
            for drive in self.drives.values():
                drive.boot()
            for spec in self.sim.faults:
                if spec.kind == FaultKind.NEVER_BOOTS:
                    self._fault_log.append(FaultRecord(spec, 0.0, self.clock.now()))
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        """Detach from the bus and stop the timer and integrator threads (never raises)."""
        if self._integrator is not None:
            self._integrator.stop()
            self._integrator = None
        if self.clock.lockstep is not None:
            self.clock.lockstep.detach("drives")
        self.clock.stop()
        if self._network is not None:
            release_quietly(
                self._network.disconnect, "simulated cell: disconnect", logger, logging.WARNING
            )
            self._network = None

    # --- results --------------------------------------------------------------------------------
    @property
    def errors(self) -> list[str]:
        """Exceptions raised inside the simulator's bus callbacks (empty when all is well)."""
        return list(self._errors)

    def fault_log(self) -> list[FaultRecord]:
        """Injected faults that took effect, in order."""
        with self._lock:
            return list(self._fault_log)

    @property
    def dropped_s(self) -> float:
        """Simulated time the realtime clock has dropped because the machine fell behind, s
        (0 in lockstep and once stopped)."""
        integrator = self._integrator
        return 0.0 if integrator is None else integrator.dropped_s

    def joint_torque_history(self) -> SimHistory:
        """The simulated truth at every SYNC so far (the last ``history_s`` seconds).

        A SYNC whose TPDOs the master has received is included: its row is written after the
        TPDOs are sent (the drives answer first), so this waits for a SYNC still being handled.
        """
        with self._physics_lock, self._lock:
            rows = list(self._history)
        n = self.robot.n
        if not rows:
            empty = np.zeros((0, n))
            return SimHistory(
                np.zeros(0, int), np.zeros(0, int), np.zeros(0), *(empty.copy() for _ in range(9))
            )
        cols = list(zip(*rows, strict=True))
        return SimHistory(
            sync_index=np.array(cols[0], dtype=int),
            counter=np.array(cols[1], dtype=int),
            time_s=np.array(cols[2], dtype=float),
            q=np.array(cols[3]),
            qd=np.array(cols[4]),
            qdd=np.array(cols[5]),
            tau=np.array(cols[6]),
            current_reference=np.array(cols[7]),
            current=np.array(cols[8]),
            setpoint=np.array(cols[9]),
            current_reference_mean=np.array(cols[10]),
            tau_mean=np.array(cols[11]),
        )

    def locked(self) -> threading.RLock:
        """The lock of the physics and the drives' state, to read them from another thread."""
        return self._physics_lock

    # --- services used by the drives --------------------------------------------------------------
    def guard(self, fn: Callable[..., None], *args: Any) -> None:
        """Run a callback; record instead of propagating its exception (python-can's notifier
        and canopen's dispatcher would otherwise drop the other callbacks of the frame)."""
        try:
            with self._physics_lock:
                fn(*args)
        except Exception as exc:
            name = getattr(fn, "__qualname__", repr(fn))
            self._errors.append(f"{name}: {exc!r}")
            logger.exception("simulated cell: %s failed", name)

    def set_heartbeat(self, drive: SimDrive, period_s: float) -> None:
        """(Re)start the heartbeat producer of ``drive`` (0 stops it)."""
        drive.heartbeat_generation += 1
        drive.heartbeat_period_s = period_s
        if period_s > 0.0 and self.clock.running:
            generation = drive.heartbeat_generation
            due = self.clock.now() + period_s
            self.clock.call_at(due, lambda: self._heartbeat(drive, generation, due))

    def _heartbeat(self, drive: SimDrive, generation: int, due: float) -> None:
        if generation != drive.heartbeat_generation:
            return
        network = self._network
        if network is None:
            return
        if not drive.heartbeat_stopped and drive.nmt != NmtState.INITIALISING:
            network.send_message(0x700 + drive.node_id, bytes([int(drive.nmt)]))
        period = drive.heartbeat_period_s
        nxt = due + period
        now = self.clock.now()
        if nxt < now:
            nxt = now + period
        self.clock.call_at(nxt, lambda: self._heartbeat(drive, generation, nxt))

    def watch_producer(self, node_id: int) -> None:
        """Hand the heartbeats of ``node_id`` to the drives' consumers (0x1016)."""
        if node_id and node_id not in self._watched and self._network is not None:
            self._watched.add(node_id)
            self._network.subscribe(0x700 + node_id, self._on_producer)

    def _on_producer(self, can_id: int, data: bytearray, timestamp: float) -> None:
        sent = self.clock.stamp(timestamp)
        for drive in self.drives.values():
            if drive.consumer.producer == can_id - 0x700:
                self.guard(drive.on_producer_heartbeat, sent)

    def watch_ramps(self) -> None:
        """A fault reaction ramps a motor to rest: without SYNC (the master is gone) the cell
        integrates it and ends it itself, one period at a time."""
        if not self._ramp_watch and self.clock.running:
            self._ramp_watch = True
            self.clock.call_at(self.clock.now() + self.period_s, self._ramp_tick)

    def _ramp_tick(self) -> None:
        self.advance_to_now()
        self._end_ramps()
        if self.physics.any_quick_stop:
            self.clock.call_at(self.clock.now() + self.period_s, self._ramp_tick)
        else:
            self._ramp_watch = False
            logger.warning(
                "simulated drives: quick stop ended, largest joint speed %.3g rad/s",
                float(np.abs(self.physics.qd).max()),
            )

    def _end_ramps(self) -> None:
        if not self.physics.any_quick_stop:  # (every SYNC: nothing to end, most of the time)
            return
        done = self.physics.quick_stop_done()
        for drive in self.drives.values():
            if done[drive.joint]:
                drive.apply_quick_stop_end()

    def advance_to_now(self) -> None:
        """Integrate the physics up to the cell's clock (caller holds the physics lock); in
        lockstep without a shared clock (drives in their own process), one period per call."""
        if self.sim.clock == Clock.REALTIME:
            self.catch_up()
        elif self.clock.lockstep is None:
            self.physics.advance(self.substeps)
        else:
            target = math.floor(self.clock.now() / self.dt + 1e-6)
            self.physics.advance(target - self.physics.step_index)

    # --- SYNC -------------------------------------------------------------------------------------
    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.guard(self._sync, bytes(data), timestamp)

    def _sync(self, data: bytes, timestamp: float | None = None) -> None:
        network = self._network
        if network is None:
            return
        counter = data[0] if data else 0
        ph = self.physics
        latched: float | None = None  # simulated time of the SYNC instant, s
        if self.clock.lockstep is not None:
            t = self.clock.lockstep.sync_instant(self.period_s, self.dt)
            ph.advance(round(t / self.dt) - ph.step_index)
        elif self.sim.clock == Clock.LOCKSTEP:
            ph.advance(self.substeps)
        elif timestamp is None:
            self.catch_up()
        else:
            # The bus stamps a SYNC when it was sent; this thread may run later (other threads,
            # the scheduler). A drive latches its position at the SYNC: report that one, or the
            # master sees speeds scaled by this thread's jitter. The physics usually covers
            # that instant already (see the end of this method); otherwise it catches up to it,
            # no further: the drives' answer waits for no more computation than that.
            latched = timestamp - time.time() + (time.monotonic() - self._t0)
            ph.advance(math.ceil(latched / self.dt) - ph.step_index)
        if self._t_first is None:
            self._t_first = ph.time_s
        sim_t = ph.time_s - self._t_first
        self._trigger_faults(sim_t, network)

        # A drive transmits what it sampled at the SYNC first and runs its control update
        # afterwards: the master gets the feedback without waiting for the drives' computation.
        for drive in self.drives.values():
            drive.begin_sync(counter)
        i_mean, tau_mean = ph.take_period_means()
        self._publish_samples(i_mean, latched)
        self._send_tpdos(network)

        latches = [drive.latch() for drive in self.drives.values()]  # joint order
        mask = np.array([t is not None for t in latches])
        targets = np.array([t or 0 for t in latches], dtype=float) / self._cpr  # motor rad
        ph.latch_targets(targets, mask, self.period_s)
        self._end_ramps()
        out = ph.evaluate()
        fe_counts = np.rint(out.following_error * self._cpr).astype(int).tolist()
        for drive in self.drives.values():
            drive.check_following_error(fe_counts[drive.joint], sim_t)
        out = ph.evaluate()  # again: a fault just raised brakes a motor
        with self._lock:
            self._history.append(
                (
                    self._sync_index,
                    counter,
                    ph.time_s,
                    ph.q.copy(),
                    ph.qd.copy(),
                    out.qdd,
                    out.tau,
                    out.current_reference,
                    out.current,
                    ph.kinv @ out.setpoint,
                    i_mean,
                    tau_mean,
                )
            )
        self._sync_index += 1
        if latched is not None:
            # The motion up to the next SYNC depends only on what was latched now: compute it
            # while the master is busy with this cycle, not when that SYNC comes.
            ph.advance(math.ceil((latched + self.period_s) / self.dt) - ph.step_index)

    def _send_tpdos(self, network: canopen.Network) -> None:
        due: list[can.Message] = []
        for drive in self.drives.values():
            for number, cob_id, payload in drive.tpdo_frames():
                if number in drive.tpdo_dropped:
                    continue
                delay = drive.tpdo_delay.get(number, 0.0)
                if delay > 0.0 and self.clock.running:
                    self.clock.call_at(
                        self.clock.now() + delay,
                        functools.partial(self._send_late, cob_id, payload),
                    )
                else:
                    due.append(
                        can.Message(is_extended_id=False, arbitration_id=cob_id, data=payload)
                    )
        if not due:
            return
        # The frames network.send_message would make, sent under one hold of its lock: a TPDO
        # burst is the cell's most frequent send.
        bus = network.bus
        assert bus is not None
        with network.send_lock:
            for msg in due:
                bus.send(msg)
        network.check()

    def catch_up(self) -> None:
        """Realtime clock: integrate up to the present (caller holds the physics lock)."""
        target = int((time.monotonic() - self._t0) / self.dt)
        self.physics.advance(target - self.physics.step_index)

    def _send_late(self, cob_id: int, payload: bytes) -> None:
        if self._network is not None:
            self._network.send_message(cob_id, payload)

    def _publish_samples(self, i_mean: np.ndarray | None = None, at: float | None = None) -> None:
        """Measured values every drive reports (SDO reads and TPDOs) at this instant.

        ``i_mean`` is the current reference averaged over the SYNC period just ended (A); the
        torque demand reports it. Outside SYNC (start-up) the instantaneous value is used.
        ``at``: position and speed are those latched at that simulated time (the SYNC instant,
        s) rather than the present ones.
        """
        ph = self.physics
        # no acceleration: a SYNC latches new targets next, which changes the step's outputs
        out = ph.evaluate(accel=False)
        if i_mean is None:
            i_mean = out.current_reference
        xm, xmd = ph.motor_state_at(ph.time_s if at is None else at)
        rated_a = np.array([d.rated_ma for d in self.drives.values()]) / 1000.0  # joint order
        # counts, and per mille of the rated current; rounded half to even (as round()), ints
        cpr = self._cpr
        rows = [xm * cpr, xmd * cpr, out.setpoint * cpr, out.following_error * cpr]
        rows += [i_mean / rated_a * 1000.0, out.current / rated_a * 1000.0]
        counts, vel, demand, fe, torque_demand, current = np.rint(rows).astype(np.int64).tolist()
        for drive in self.drives.values():
            j = drive.joint
            drive.sample = {
                ob.POSITION_ACTUAL: counts[j],
                ob.VELOCITY_ACTUAL: vel[j],
                ob.POSITION_DEMAND: demand[j],
                ob.FOLLOWING_ERROR_ACTUAL: fe[j],
                ob.TORQUE_DEMAND: torque_demand[j],
                ob.CURRENT_ACTUAL: current[j],
                ob.TORQUE_ACTUAL: current[j],
            }

    # --- faults -----------------------------------------------------------------------------------
    def _trigger_faults(self, sim_t: float, network: canopen.Network) -> None:
        due = [s for s in self._pending_faults if s.at_s <= sim_t + 1e-12]
        if not due:
            return
        self._pending_faults = [s for s in self._pending_faults if s not in due]
        for spec in due:
            drive = self.drives.get(spec.node) if spec.node is not None else None
            if spec.kind == FaultKind.EMCY and drive is not None:
                drive.inject_fault(spec.effective_code or 0, emcy=True)
            elif spec.kind == FaultKind.FAULT and drive is not None:
                drive.inject_fault(spec.effective_code or 0, emcy=False)
            elif spec.kind == FaultKind.HEARTBEAT_STOP and drive is not None:
                drive.heartbeat_stopped = True
            elif spec.kind == FaultKind.TPDO_MISSING and drive is not None:
                drive.tpdo_dropped |= {spec.tpdo} if spec.tpdo else {1, 2, 3, 4}
            elif spec.kind == FaultKind.TPDO_LATE and drive is not None:
                for number in (spec.tpdo,) if spec.tpdo else (1, 2, 3, 4):
                    drive.tpdo_delay[number] = spec.delay_s
            elif spec.kind == FaultKind.BUS_ERROR:
                frame = can.Message(
                    arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, data=bytes(8)
                )
                with network.send_lock:
                    assert network.bus is not None
                    network.bus.send(frame)
            with self._lock:
                self._fault_log.append(FaultRecord(spec, sim_t, self.clock.now()))
