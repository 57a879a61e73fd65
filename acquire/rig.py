"""Bring-up and tear-down of a cell: the CAN network, the simulated drives if any, the master.

The same code drives hardware and simulation; the configuration decides (``[bus]`` and the
optional ``[simulation]`` table).
"""

from __future__ import annotations

import dataclasses
import logging
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import canopen

from drivegain.acquire.cantrace import can_trace
from drivegain.acquire.config import AcquisitionConfig
from drivegain.drivers.bus import open_network
from drivegain.drivers.clock import Clock
from drivegain.drivers.ipcbus import INTERFACE as IPC_INTERFACE
from drivegain.drivers.master import DriveEvent, Master, MasterHeartbeat, Timeouts
from drivegain.drivers.realtime import RealtimePolicy
from drivegain.drivers.sim import SimConfig, SimulatedCell
from drivegain.drivers.simprocess import SimulatedCellProcess, drives_in_child_process
from drivegain.lifecycle import Closing, release_quietly

log = logging.getLogger(__name__)


def simulation_for_run(sim: SimConfig, payload: Path | None, seed: int | None = None) -> SimConfig:
    """The simulation settings of one run.

    A payload named in ``[simulation]`` is what the simulated robot carries whatever the run
    declares (to rehearse a wrong declaration); otherwise it carries the run's payload, as a real
    robot carries what the operator mounted.
    """
    changes: dict[str, Any] = {}
    if sim.payload is None and payload is not None:
        changes["payload"] = payload
    if seed is not None:
        changes["seed"] = seed
    return dataclasses.replace(sim, **changes) if changes else sim


def realtime_policy(cfg: AcquisitionConfig) -> RealtimePolicy:
    """The realtime policy of a configuration.

    The garbage-collector freeze always (lockstep time-outs are generous, but a full collection
    still stalls the bus reader for up to 0.26 s); SCHED_FIFO ``rt_priority`` for the cycle
    thread in realtime only, as a lockstep cycle has no deadline to keep. The interpreter's
    switch interval is left at its default (docs/realtime.md: a shorter one was measured and
    lost more cycles).
    """
    prio = cfg.rt_priority if cfg.clock == Clock.REALTIME else 0
    return RealtimePolicy(gc_freeze=True, fifo_priority=prio)


class Rig(Closing):
    """The network, the optional simulated cell and the booted master of a configuration.

    A simulated cell runs in this process on the ``virtual`` bus (and in lockstep on a vcan
    device), or in a child process on the ``drivegain-ipc`` bus and in realtime on a vcan device
    (:func:`~drivegain.drivers.simprocess.drives_in_child_process`), as ``[bus]`` and
    ``[simulation] clock`` say.

    Parameters
    ----------
    cfg
        The acquisition configuration.
    simulation
        Overrides ``cfg.simulation`` (e.g. :func:`simulation_for_run`); ignored on hardware.
    policy
        The realtime policy (default :func:`realtime_policy` of ``cfg``). The rig enters its
        process part from :meth:`open` to :meth:`close`, so a daemon that keeps the rig keeps
        the garbage-collector freeze across its runs; sessions on the rig's master take their
        cycle thread's scheduling from it (:attr:`policy`), and simulated drives in a child
        process enter the same policy there.
    timeouts
        The master's time limits (default: the library's, with ``cfg.tpdo_timeout_s`` and
        ``cfg.heartbeat_timeout_s``).
    trace
        Raw CAN trace to record from :meth:`open` to :meth:`close`
        (:func:`~drivegain.acquire.cantrace.can_trace`): from before the simulated drives power
        on (on ``drivegain-ipc``, whose server is their process, from just after), so every frame
        of the run is in it, shutdown included.

    Use as a context manager, or call :meth:`open` and :meth:`close` (which never raises).
    """

    def __init__(
        self,
        cfg: AcquisitionConfig,
        simulation: SimConfig | None = None,
        policy: RealtimePolicy | None = None,
        timeouts: Timeouts | None = None,
        trace: Path | None = None,
    ):
        self.cfg = cfg
        self.trace = trace
        self.simulation = simulation if simulation is not None else cfg.simulation
        self.policy = policy if policy is not None else realtime_policy(cfg)
        self.timeouts = (
            timeouts
            if timeouts is not None
            else Timeouts(tpdo_s=cfg.tpdo_timeout_s, heartbeat_s=cfg.heartbeat_timeout_s)
        )
        self.cell: SimulatedCell | SimulatedCellProcess | None = None
        self.network: canopen.Network | None = None
        self.master: Master | None = None
        self.boot_events: list[DriveEvent] = []
        self._realtime: ExitStack | None = None
        self._trace: ExitStack | None = None

    def open(self) -> Master:
        """Start the simulated drives (if any), connect, boot every drive.

        Raises
        ------
        DriveError
            A drive does not boot or answer (node id in the error); everything opened is closed.
        """
        cfg = self.cfg
        try:
            # before any drive thread starts: they inherit its CPU set, and boot's time-outs
            # are already shorter than a full collection
            self._realtime = ExitStack()
            self._realtime.enter_context(self.policy.process())
            self._trace = ExitStack()
            # the trace listens from before the drives power on, but on drivegain-ipc, whose
            # server is the drives' process, from just after
            trace_after_cell = cfg.bus.interface == IPC_INTERFACE
            if not trace_after_cell:
                self._trace.enter_context(can_trace(cfg.bus, self.trace))
            if self.simulation is not None:
                sim = self.simulation
                if drives_in_child_process(cfg.bus, sim):
                    self.cell = SimulatedCellProcess(
                        cfg.robot, cfg.bus, sim, cfg.period_s, eds=cfg.eds, policy=self.policy
                    )
                else:
                    self.cell = SimulatedCell(cfg.robot, cfg.bus, sim, cfg.period_s, eds=cfg.eds)
                self.cell.start()
            if trace_after_cell:
                self._trace.enter_context(can_trace(cfg.bus, self.trace))
            self.network = open_network(cfg.bus)
            # in lockstep with the drives in this process, the master counts their simulated
            # time (every supervision time-out); otherwise the wall clock
            clock = self.cell.clock.lockstep if isinstance(self.cell, SimulatedCell) else None
            self.master = Master(
                cfg.robot,
                self.network,
                period_s=cfg.period_s,
                eds=cfg.eds,
                timeouts=self.timeouts,
                heartbeat=MasterHeartbeat(cfg.master_node_id, cfg.master_heartbeat_s),
                clock=clock,
            )
            self.master.boot()
            self.boot_events = list(self.master.drain_events())
            # the booted cell lives as long as the freeze: later collections need not walk it
            self.policy.refreeze()
        except BaseException:
            self.close()
            raise
        log.info(
            "%d drives booted on %s:%s (%s)",
            cfg.robot.n,
            cfg.bus.interface,
            cfg.bus.channel,
            "simulated" if self.cell is not None else "hardware",
        )
        return self.master

    def close(self) -> None:
        """Disable and release everything; never raises."""
        if self.master is not None:
            release_quietly(self.master.close, "closing the master", log)
            self.master = None
        if self.network is not None:
            release_quietly(self.network.disconnect, "disconnecting the network", log)
            self.network = None
        if self.cfg.bus.interface == IPC_INTERFACE:
            self._close_trace()  # before the drives go: on drivegain-ipc they are the bus
        if self.cell is not None:
            release_quietly(self.cell.stop, "stopping the simulated drives", log)
            self.cell = None
        self._close_trace()  # after the drives: their last heartbeats are in it
        if self._realtime is not None:
            release_quietly(self._realtime.close, "leaving the realtime policy", log)
            self._realtime = None

    def _close_trace(self) -> None:
        if self._trace is not None:
            release_quietly(self._trace.close, "closing the CAN trace", log)
            self._trace = None

    def __enter__(self) -> Master:
        return self.open()
