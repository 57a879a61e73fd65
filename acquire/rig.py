"""Bring-up and tear-down of a cell: the CAN network, the simulated drives if any, the master.

The same code drives hardware and simulation; the configuration decides (``[bus]`` and the
optional ``[simulation]`` table).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from types import TracebackType
from typing import Any

import canopen

from drivegain.acquire.config import AcquisitionConfig
from drivegain.drivers.bus import open_network
from drivegain.drivers.ipcbus import INTERFACE as IPC_INTERFACE
from drivegain.drivers.master import DriveEvent, Master, Timeouts
from drivegain.drivers.sim import SimConfig, SimulatedCell
from drivegain.drivers.simprocess import SimulatedCellProcess

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


class Rig:
    """The network, the optional simulated cell and the booted master of a configuration.

    A simulated cell runs in this process on the ``virtual`` bus, or in a child process on the
    ``drivegain-ipc`` bus (:mod:`drivegain.drivers.simprocess`), as ``[bus]`` says.

    Parameters
    ----------
    cfg
        The acquisition configuration.
    simulation
        Overrides ``cfg.simulation`` (e.g. :func:`simulation_for_run`); ignored on hardware.

    Use as a context manager, or call :meth:`open` and :meth:`close` (which never raises).
    """

    def __init__(self, cfg: AcquisitionConfig, simulation: SimConfig | None = None):
        self.cfg = cfg
        self.simulation = simulation if simulation is not None else cfg.simulation
        self.cell: SimulatedCell | SimulatedCellProcess | None = None
        self.network: canopen.Network | None = None
        self.master: Master | None = None
        self.boot_events: list[DriveEvent] = []

    def open(self) -> Master:
        """Start the simulated drives (if any), connect, boot every drive.

        Raises
        ------
        DriveError
            A drive does not boot or answer (node id in the error); everything opened is closed.
        """
        cfg = self.cfg
        try:
            if self.simulation is not None:
                host = SimulatedCellProcess if cfg.bus.interface == IPC_INTERFACE else SimulatedCell
                self.cell = host(cfg.robot, cfg.bus, self.simulation, cfg.period_s, eds=cfg.eds)
                self.cell.start()
            self.network = open_network(cfg.bus)
            self.master = Master(
                cfg.robot,
                self.network,
                period_s=cfg.period_s,
                eds=cfg.eds,
                timeouts=Timeouts(tpdo_s=cfg.tpdo_timeout_s),
            )
            self.master.boot()
            self.boot_events = list(self.master.drain_events())
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
            try:
                self.master.close()
            except Exception as exc:
                log.error("closing the master failed: %s", exc)
            self.master = None
        if self.network is not None:
            try:
                self.network.disconnect()
            except Exception as exc:
                log.error("disconnecting the network failed: %s", exc)
            self.network = None
        if self.cell is not None:
            try:
                self.cell.stop()
            except Exception as exc:
                log.error("stopping the simulated drives failed: %s", exc)
            self.cell = None

    def __enter__(self) -> Master:
        return self.open()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
