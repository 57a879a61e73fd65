"""One acquisition session: checks, enable, approach / excitation / retreat, disable, finished log.

The cycle loop runs on the thread that calls :meth:`Session.run` (one thread; the caller starts a
dedicated one). Each cycle: wait for the deadline (``realtime``) or not at all (``lockstep``), send
the setpoints and SYNC, collect TPDOs, supervise, hand the cycle to the recorder thread. Lockstep
takes the TPDOs of the SYNC just sent (:meth:`Master.cycle`); realtime is pipelined
(:meth:`Master.cycle_pipelined`): after SYNC k the TPDOs of cycle k−1 are recorded against cycle
k−1 (its ``cycle``, ``t``, SYNC time, setpoint) and supervised, a period later
(docs/realtime.md). Faults (drive, bus, supervision, recorder) quick-stop every drive and finish
the log with the fault as its last event; an operator stop decelerates to rest with a
jerk-limited ruckig profile, disables and finishes the log with the stop recorded.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from drivegain.acquire.checks import check_bus_load, check_motion
from drivegain.acquire.config import AcquisitionConfig
from drivegain.acquire.pacing import LockstepPacer, Pacer, RealtimePacer
from drivegain.acquire.recorder import (
    CycleRecord,
    EventRecord,
    Recorder,
    RecorderError,
    RecorderOverrun,
)

# the request and its checks live in .request; importers of the session module still find them
from drivegain.acquire.request import PreparedRun as PreparedRun
from drivegain.acquire.request import RunRequest as RunRequest
from drivegain.acquire.request import prepare_run as prepare_run
from drivegain.acquire.request import validate_label as validate_label
from drivegain.acquire.rig import realtime_policy
from drivegain.acquire.stats import LoopStats
from drivegain.acquire.stop import StopRequest
from drivegain.acquire.supervision import Supervisor
from drivegain.drivers.clock import Clock
from drivegain.drivers.master import CycleSample, DriveEvent, Master
from drivegain.drivers.objects import EmcyCode
from drivegain.drivers.realtime import RealtimePolicy
from drivegain.errors import DriveError, DrivegainError, OperatorStop
from drivegain.excite.motion import Motion, Phase
from drivegain.excite.motion import plan_stop as plan_stop_motion
from drivegain.excite.trajectory import plan_excitation
from drivegain.formats.log import EventLevel, run_metadata, utc_now_iso
from drivegain.formats.logwriter import LogWriter

log = logging.getLogger(__name__)

#: what the master's event says about a TPDO that arrived after its cycle was over
_STALE_TPDO = "arrived during SYNC"
#: the levels of drive events; one the log does not know is kept as an error (the safe side)
_LEVELS = {level.value: level for level in EventLevel}


class RunState(StrEnum):
    """Where a session is. ``FINISHED``, ``STOPPED`` and ``FAULT`` are final."""

    PLANNED = "planned"
    ENABLING = "enabling"
    APPROACH = "approach"
    EXCITATION = "excitation"
    RETREAT = "retreat"
    SETTLING = "settling"
    STOPPING = "stopping"
    DISABLING = "disabling"
    FINISHED = "finished"
    STOPPED = "stopped"
    FAULT = "fault"


_PHASE_STATE = {
    Phase.APPROACH: RunState.APPROACH,
    Phase.EXCITATION: RunState.EXCITATION,
    Phase.RETREAT: RunState.RETREAT,
    Phase.STOP: RunState.STOPPING,
}


class AcquisitionFault(DriveError):
    """The cycle loop itself cannot go on (missed deadlines, operator quick stop)."""


@dataclass
class RunResult:
    """The outcome of a session (also kept on the session when it raised)."""

    path: Path | None
    state: RunState
    cycles: int
    stats: dict[str, str] = field(default_factory=dict)
    stop_reason: str | None = None
    fault: str | None = None
    max_following_error: list[float] = field(default_factory=list)


@dataclass(frozen=True)
class _Sent:
    """A cycle the loop sent: what its record needs besides the drives' answers."""

    cycle: int
    setpoint: np.ndarray  # rad, sent with its SYNC
    log_ns: int  # the pacer's log time of the cycle
    interval_s: float | None  # since the previous SYNC (realtime), s


class _Setpoints:
    """Samples a motion at the cycle times, a block at a time (bounded memory)."""

    def __init__(self, motion: Motion, period_s: float, first_cycle: int, block: int = 256):
        self.motion = motion
        self.period_s = period_s
        self.first = first_cycle
        self.block = block
        self._start = -1
        self._q = self._qd = self._qdd = np.empty((0, 0))

    def t(self, cycle: int) -> float:
        """Time into the motion of ``cycle``, s."""
        return (cycle - self.first) * self.period_s

    def done(self, cycle: int) -> bool:
        return self.t(cycle) > self.motion.duration_s + 1e-12

    def state(self, cycle: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Setpoint position, velocity and acceleration of ``cycle`` (held after the end)."""
        i = cycle - self.first
        if not self._start <= i < self._start + len(self._q):
            self._start = i
            t = (i + np.arange(self.block)) * self.period_s
            self._q, self._qd, self._qdd = self.motion.sample(np.minimum(t, self.motion.duration_s))
        j = i - self._start
        return self._q[j], self._qd[j], self._qdd[j]


class Session:
    """One run on a booted master.

    Parameters
    ----------
    cfg
        The acquisition configuration.
    master
        A booted master (the caller owns it: boot before, close after).
    prepared
        The checked request (:func:`prepare_run`).
    stop
        Operator stop requests (signals, daemon ``stop``), polled every cycle.
    pre_events
        Drive events seen before the run (boot...), written at the start of the log.
    on_cycle
        Called on the cycle thread after every cycle with the session (progress displays);
        must be quick.
    policy
        The realtime policy of the rig that owns ``master`` (``Rig.policy``; default
        :func:`~drivegain.acquire.rig.realtime_policy` of ``cfg``). The run enters its cycle
        thread part (SCHED_FIFO); its process part (garbage-collector freeze) is the rig's.
    pipelined
        Collect each cycle's TPDOs one cycle later (:meth:`Master.cycle_pipelined`); default:
        in realtime, not in lockstep. With the SYNC echo, RPDOs go out ahead (:meth:`Master.stage`).

    Attributes
    ----------
    held_cycles
        Cycles whose last TPDO came too late for the loop: after the next SYNC was due (same
        cycle, or pipelined without the SYNC echo), after the one after it (pipelined).
    """

    def __init__(
        self,
        cfg: AcquisitionConfig,
        master: Master,
        prepared: PreparedRun,
        *,
        stop: StopRequest | None = None,
        pre_events: Sequence[DriveEvent] = (),
        on_cycle: Callable[[Session], None] | None = None,
        policy: RealtimePolicy | None = None,
        pipelined: bool | None = None,
    ):
        self.cfg = cfg
        self.pipelined = cfg.clock != Clock.LOCKSTEP if pipelined is None else pipelined
        self.held_cycles = 0
        self._after_sync = self.pipelined and master is not None and master.layout.tagged
        self.robot = cfg.robot
        self.master = master
        self.prepared = prepared
        self.stop = stop if stop is not None else StopRequest()
        self.on_cycle = on_cycle
        self.policy = policy if policy is not None else realtime_policy(cfg)
        self._pre_events = list(pre_events)
        self.state = RunState.PLANNED
        self.cycle = 0
        self.t = 0.0
        self.motion: Motion | None = None
        self.duration_s = 0.0
        self.result: RunResult | None = None
        self.stats = LoopStats(period_s=cfg.period_s, clock=cfg.clock)
        self.supervisor = Supervisor(self.robot, cfg.supervision, cfg.period_s)
        self.bus_load = prepared.bus_load
        self._warnings = list(prepared.warnings)
        self._recorder: Recorder | None = None
        self._pacer: Pacer | None = None

    # -- planning ------------------------------------------------------------------------------

    def plan(self) -> Motion:
        """Plan approach + excitation + retreat from the drives' actual positions and check it.

        Raises
        ------
        TrajectoryError
            The motion from here would violate a limit (names the joint and limit).
        """
        cfg = self.cfg
        # the same check as before the bus was touched, now with the drives' actual mapping
        load, warning = check_bus_load(
            self.robot.n,
            cfg.period_s,
            cfg.bus.bitrate,
            warn=cfg.bus_load_warn,
            config=cfg.source,
            load=self.master.bus_load(cfg.bus.bitrate),
        )
        self.bus_load = load
        if warning and warning not in self._warnings:
            self._warnings.append(warning)
        q0 = np.asarray(self.master.read_positions(), dtype=float)
        motion = plan_excitation(self.prepared.excitation, self.robot, q0)
        check_motion(self.robot, motion, self.cfg.period_s)
        self.motion = motion
        self.duration_s = motion.duration_s + self.cfg.settle_s
        return motion

    # -- the run -------------------------------------------------------------------------------

    def run(self) -> RunResult:
        """Enable, stream the motion, disable, finish the log.

        Returns
        -------
        RunResult
            ``state`` FINISHED, or STOPPED after an operator stop.

        Raises
        ------
        DriveError
            A drive, bus or supervision fault (after the quick stop and the finished log).
        RecorderError
            The log could not be written (the drives are quick-stopped).
        """
        if self.motion is None:
            self.plan()
        assert self.motion is not None
        cfg, prep = self.cfg, self.prepared
        prep.request.out.parent.mkdir(parents=True, exist_ok=True)
        meta = run_metadata(
            self.robot,
            prep.label,
            prep.payload,
            cfg.period_s,
            utc_now_iso(),
            extra={
                "clock": cfg.clock,
                "bus_interface": cfg.bus.interface,
                "bus_channel": cfg.bus.channel,
                "bitrate": str(cfg.bus.bitrate),
                "bus_load": f"{self.bus_load.load:.3f}",
                "trajectory": prep.request.trajectory.name,
                **(
                    {"can_trace": prep.request.can_trace.name}
                    if prep.request.can_trace is not None
                    else {}
                ),
                "host": os.uname().nodename,
            },
        )
        writer = LogWriter(prep.request.out, meta, prep.attachments)
        recorder = Recorder(
            writer, capacity=cfg.queue_capacity, flush_interval_s=cfg.flush_interval_s
        )
        self._recorder = recorder
        pacer: Pacer
        if cfg.clock == Clock.LOCKSTEP:
            pacer = LockstepPacer(cfg.period_s, self.stats)
        else:
            pacer = RealtimePacer(cfg.period_s, self.stats, spin_s=cfg.spin_s)
        self._pacer = pacer
        pacer.start()
        recorder.start()
        # the quick stop of a fault still runs at the cycle's priority; the disabling of a
        # normal end at the caller's (nothing is late any more)
        with self.policy.cycle_thread() as fifo:
            try:
                started = f"run '{prep.label}' started"
                self._event(EventLevel.INFO, started, duration_s=f"{self.duration_s:.3f}")
                for w in self._warnings:
                    log.warning("%s", w)
                    self._event(EventLevel.WARNING, w)
                self._drive_events(self._pre_events)
                if fifo.refusal is not None:
                    text = (
                        f"cannot use SCHED_FIFO priority {fifo.priority} ({fifo.refusal}): "
                        "running at normal priority"
                    )
                    log.warning("%s", text)
                    self._event(EventLevel.WARNING, text)
                self.state = RunState.ENABLING
                self.master.enable()
                self._drive_events(self.master.drain_events())
                self._loop(pacer, recorder)
            except BaseException as exc:
                self._on_fault(exc, recorder)
                raise
        return self._finish_ok(recorder)

    def _loop(self, pacer: Pacer, recorder: Recorder) -> None:
        started = time.monotonic()
        pacer.anchor()
        try:
            self._cycles(pacer, recorder)
        finally:
            self.stats.wall_s = time.monotonic() - started

    def _cycles(self, pacer: Pacer, recorder: Recorder) -> None:
        assert self.motion is not None
        cfg = self.cfg
        lockstep = cfg.clock == Clock.LOCKSTEP
        setpoints = _Setpoints(self.motion, cfg.period_s, 0)
        settle_cycles = round(cfg.settle_s / cfg.period_s)
        period_ns = round(cfg.period_s * 1e9)
        stopping = False
        end_cycle: int | None = None
        phase: Phase | None = None
        last_send = 0
        in_flight: _Sent | None = None  # pipelined: the cycle sent, not recorded yet
        k = 0
        while True:
            if self.stop.requested and not stopping:
                setpoints = self._begin_stop(setpoints, k)
                stopping = True
                end_cycle = None
            if stopping and self.stop.urgent:
                raise AcquisitionFault(f"operator quick stop ({self.stop.reason}, requested twice)")
            if end_cycle is None and setpoints.done(k):
                end_cycle = k + settle_cycles
                if not stopping:
                    self.state = RunState.SETTLING
            if end_cycle is not None and k >= end_cycle:
                break
            if not stopping and end_cycle is None:
                ph = self.motion.phase(setpoints.t(k))
                if ph != phase and ph in _PHASE_STATE:
                    phase = ph
                    self.state = _PHASE_STATE[ph]
                    self._event(EventLevel.INFO, f"phase {ph.name.lower()}", phase=ph.name.lower())
            q_sp = setpoints.state(k)[0]
            if self._after_sync:  # RPDOs before the deadline, the SYNC alone at it
                self.master.stage(q_sp)
            log_ns = pacer.wait(k)
            if isinstance(pacer, RealtimePacer) and (
                pacer.consecutive_overruns > cfg.supervision.max_overruns
            ):
                raise AcquisitionFault(
                    f"{pacer.consecutive_overruns} consecutive cycles missed their deadline "
                    f"by more than one period (cycle {k})"
                )
            sample: CycleSample | None
            if self.pipelined:
                step = self.master.cycle_pipelined(q_sp)
                sync_s, sample = step.sent.sync_monotonic_s, step.sample
            else:
                sample = self.master.cycle(q_sp)
                sync_s = sample.sync_monotonic_s
            # between the SYNCs themselves (a stall before this SYNC went out counts)
            sent = round(sync_s * 1e9)
            pacer.sync_sent(k, sent)
            interval_s = (sent - last_send) / 1e9 if k > 0 and not lockstep else None
            self.stats.cycles += 1
            if k > 0 and not lockstep:
                self.stats.sync_dev.add(abs(sent - last_send - period_ns))
            last_send = sent
            this = _Sent(k, q_sp, log_ns, interval_s)
            if sample is not None:  # pipelined: the previous cycle's, None on the first
                self._record(sample, in_flight if self.pipelined else this, recorder)
            if self.pipelined:
                in_flight = this
            if self.on_cycle is not None:
                self.on_cycle(self)
            k += 1
        if in_flight is not None:
            # the last SYNC's answers: after it, nothing is sent any more
            last = self.master.collect_pending()
            if last is not None:
                self._record(last, in_flight, recorder)
        self.cycle = k

    def _record(self, sample: CycleSample, sent: _Sent | None, recorder: Recorder) -> None:
        """Record and supervise ``sample``, the drives' answers to the SYNC ``sent``."""
        assert sent is not None
        cfg, lockstep = self.cfg, self.cfg.clock == Clock.LOCKSTEP
        k = sent.cycle
        self.stats.service.add(round(sample.latency_s * 1e9))
        if sample.latency_s > cfg.period_s:
            self.stats.late_cycles += 1
        # pipelined with the SYNC echo, a cycle's TPDOs are waited for after the next SYNC
        if sample.latency_s > (1 + self._after_sync) * cfg.period_s:
            self.held_cycles += 1
        # the SYNC's own wall-clock time in realtime, simulated time in lockstep
        log_ns = sent.log_ns if lockstep else sample.sync_time_ns
        recorder.put_cycle(
            CycleRecord(
                cycle=k,
                t=k * cfg.period_s,
                log_time_ns=log_ns,
                position=np.asarray(sample.position, dtype=float),
                current_reference=np.asarray(sample.current_reference, dtype=float),
                current=np.asarray(sample.current, dtype=float),
                setpoint=np.array(sent.setpoint, dtype=float),
                raw=sample.raw,
            ),
            block=lockstep,
        )
        self.cycle, self.t = k, k * cfg.period_s
        # after recording: the cycle that shows the fault is in the log
        self.supervisor.check(k, sample.position, sent.setpoint, sent.interval_s)
        self._drive_events(self.master.drain_events())

    def _begin_stop(self, setpoints: _Setpoints, k: int) -> _Setpoints:
        """Plan the deceleration to rest from the setpoint state of the last cycle sent."""
        q, qd, qdd = setpoints.state(max(k - 1, 0))
        if k == 0:
            qd, qdd = np.zeros_like(q), np.zeros_like(q)
        stop_motion = plan_stop_motion(self.robot, q, qd, qdd)
        self.state = RunState.STOPPING
        self._event(
            EventLevel.WARNING,
            f"operator stop ({self.stop.reason}): decelerating to rest in "
            f"{stop_motion.duration_s:.2f} s",
            reason=self.stop.reason or "",
            cycle=k,
        )
        log.warning("operator stop (%s): decelerating to rest", self.stop.reason)
        for w in stop_motion.warnings:
            self._event(EventLevel.WARNING, w)
        # the stop starts from the state of cycle k-1, so its t = 0 is that cycle: cycle k
        # continues one period into it (no repeated setpoint, no velocity jump)
        return _Setpoints(stop_motion, self.cfg.period_s, max(k - 1, 0))

    # -- endings -------------------------------------------------------------------------------

    def _finish_ok(self, recorder: Recorder) -> RunResult:
        stopped = self.stop.requested
        self.state = RunState.DISABLING
        try:
            self.master.disable()
            self._drive_events(self.master.drain_events())
            stats = self.stats.summary()
            self._event(EventLevel.INFO, "cycle statistics", **stats)
            if stopped:
                self._event(
                    EventLevel.WARNING,
                    f"operator stop ({self.stop.reason}): robot at rest, drives disabled",
                    reason=self.stop.reason or "",
                )
            else:
                self._event(EventLevel.INFO, f"run finished: {self.cycle} cycles")
        except BaseException as exc:
            self._on_fault(exc, recorder)
            raise
        path = recorder.finish()
        self.state = RunState.STOPPED if stopped else RunState.FINISHED
        self.result = RunResult(
            path=path,
            state=self.state,
            cycles=self.cycle,
            stats=stats,
            stop_reason=self.stop.reason if stopped else None,
            max_following_error=self.supervisor.max_following_error.tolist(),
        )
        log.info("run %s: %s, %d cycles, log %s", self.prepared.label, self.state, self.cycle, path)
        return self.result

    def _on_fault(self, exc: BaseException, recorder: Recorder) -> None:
        """Quick stop, then finish the log with the fault as its last event. Never raises."""
        # the events the drives sent up to the fault, before the quick stop adds its own
        pending: list[DriveEvent] = []
        try:
            pending = list(self.master.drain_events())
        except Exception as e:  # on the way down nothing may stop the quick stop
            log.error("draining drive events failed: %s", e)
        self.master.quick_stop()
        self.master.disable()
        self.state = RunState.FAULT
        text = str(exc) or type(exc).__name__
        node = getattr(exc, "node", None)
        code = getattr(exc, "code", None)
        log.error("fault at cycle %d: %s; all drives quick-stopped", self.cycle, text)
        if isinstance(exc, DriveError) and exc.code == int(EmcyCode.PDO_TIMEOUT) and node:
            self.stats.missing_tpdo[node] += 1
        path: Path | None = None
        writable = recorder.failed is None and (
            isinstance(exc, RecorderOverrun) or not isinstance(exc, RecorderError)
        )
        if writable:
            try:
                self._drive_events(pending)
                self._event(EventLevel.INFO, "cycle statistics", **self.stats.summary())
                fields: dict[str, Any] = {"action": "quick stop", "cycle": self.cycle}
                if not isinstance(exc, DrivegainError):
                    fields["exception"] = type(exc).__name__
                drive_state = getattr(exc, "state", None)
                if drive_state is not None:
                    fields["drive_state"] = drive_state
                self._event(EventLevel.ERROR, text, node=node, code=code, **fields)
                path = recorder.finish()
            except Exception as e:
                log.error("finishing the log after the fault failed: %s", e)
                if not recorder.closed:
                    _safe_abandon(recorder)
        else:
            _safe_abandon(recorder)
        try:
            for ev in self.master.drain_events():
                log.info("after the quick stop: node %s: %s", ev.node, ev.text)
        except Exception:
            pass
        self.result = RunResult(
            path=path,
            state=RunState.FAULT,
            cycles=self.cycle,
            stats=self.stats.summary(),
            fault=text,
            max_following_error=self.supervisor.max_following_error.tolist(),
        )

    # -- helpers -------------------------------------------------------------------------------

    def _event(
        self,
        level: EventLevel,
        text: str,
        *,
        node: int | None = None,
        code: int | None = None,
        **fields: Any,
    ) -> None:
        assert self._recorder is not None and self._pacer is not None
        self._recorder.put_event(
            EventRecord(
                log_time_ns=self._pacer.now_log_ns(),
                level=level,
                text=text,
                node=node,
                code=code,
                fields=fields,
            )
        )

    def _drive_events(self, events: Sequence[DriveEvent]) -> None:
        for ev in events:
            if ev.node is not None and _STALE_TPDO in ev.text:
                # a TPDO that came after its cycle was over: late on this node
                self.stats.late_tpdo[ev.node] += 1
            level = _LEVELS.get(ev.level, EventLevel.ERROR)
            log.log(
                logging.DEBUG if level is EventLevel.INFO else logging.WARNING,
                "node %s: %s",
                ev.node,
                ev.text,
            )
            self._event(level, ev.text, node=ev.node, code=ev.code, drive_time_ns=ev.time_ns)


def _safe_abandon(recorder: Recorder) -> None:
    try:
        recorder.abandon()
    except Exception as e:
        log.error("closing the log failed: %s", e)


def operator_stop_error(result: RunResult) -> OperatorStop:
    """The :class:`OperatorStop` a command raises after a stopped run (exit status 0)."""
    return OperatorStop(
        f"run stopped by {result.stop_reason or 'the operator'} after {result.cycles} cycles; "
        f"log finished at {result.path}"
    )
