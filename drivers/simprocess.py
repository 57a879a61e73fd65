"""The simulated cell in a child process, on the ``drivegain-ipc`` bus or a kernel vcan device.

In-process, the simulated drives share the master's interpreter lock: their physics and SYNC
handling (more than half the CPU time of a realtime run) delay the master's cycle thread, which
real drives never do. Here they run in a process of their own, like separate devices on a cable.

Which buses (:func:`drives_in_child_process`): ``drivegain-ipc`` always (the child is its
server); python-can's ``socketcan`` on a Linux ``vcan`` device when the simulation runs in
``realtime``: the child opens the configured interface itself, through the same
:func:`~drivegain.drivers.bus.open_network` as the master, and the kernel carries the frames
between the two sockets as between a controller and its drives. A realtime cell paces itself
from the wall clock and the bus time stamps, which both processes share. ``lockstep`` on
``socketcan`` keeps the drives in the master's process: lockstep's simulated clock counts the
frames each side sends and handles, which only works within one process (see
:mod:`drivegain.drivers.simtime`); a child would have to fall back to wall-clock time-outs, the
one thing lockstep is there to avoid. (On ``drivegain-ipc`` a lockstep child does exactly that;
that bus has no other use.)

The child is ``python -m drivegain.drivers.simprocess FD`` (not a multiprocessing child, which
would re-run the parent's main script), talking pickles over a socket pair. It ignores SIGINT
and SIGTERM: a Ctrl-C or a service stop reaches the whole process group,
and the drives must keep answering while the master decelerates and disables them. It stops when
the parent says so. When the parent is gone (its end of the control pipe closes: the master was
killed), the drives go on as real drives would: their consumer of the master's heartbeat (0x1016)
times out and their fault reaction brings the robot to rest; the child logs both on its standard
error, then stops (at the latest :data:`OUTLIVE_S` later).
"""

from __future__ import annotations

import logging
import signal
import socket
import subprocess
import sys
import time
import weakref
from contextlib import ExitStack
from multiprocessing.connection import Connection
from pathlib import Path

from drivegain import errors as errs
from drivegain.config.robot import Robot
from drivegain.drivers.bus import BusConfig
from drivegain.drivers.clock import Clock
from drivegain.drivers.ipcbus import INTERFACE
from drivegain.drivers.realtime import RealtimePolicy
from drivegain.drivers.sim import FaultRecord, SimConfig, SimulatedCell
from drivegain.errors import ConfigError, DriveError
from drivegain.lifecycle import Running

#: How long the child may take to import, build the simulation and listen, s.
START_TIMEOUT_S = 60.0
#: How long the child may take to stop and report, s.
STOP_TIMEOUT_S = 10.0
_POLL_S = 0.2
#: Longest the child serves its drives after the master is gone: consumer time-out plus the
#: quick stop of a fast robot, with a wide margin, s.
OUTLIVE_S = 20.0
#: Cells whose child may still run (the test suite's leak check reads it).
RUNNING: weakref.WeakSet[SimulatedCellProcess] = weakref.WeakSet()
#: python-can's interface of kernel CAN devices, where realtime drives run in a child process.
SOCKETCAN = "socketcan"


def drives_in_child_process(bus_cfg: BusConfig, sim: SimConfig) -> bool:
    """Whether the simulated drives of ``sim`` on ``bus_cfg`` run in a process of their own.

    ``drivegain-ipc``: always. ``socketcan`` (a vcan device): in ``realtime``, as separate
    devices; in ``lockstep`` they share the master's process and its simulated clock. The
    in-process ``virtual`` bus: never (it connects buses of one process only).
    """
    if bus_cfg.interface == INTERFACE:
        return True
    return bus_cfg.interface == SOCKETCAN and sim.clock == Clock.REALTIME


def _serve(
    robot: Robot,
    bus_cfg: BusConfig,
    sim: SimConfig,
    period_s: float,
    eds: Path | None,
    policy: RealtimePolicy,
    conn: Connection,
) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        cell = SimulatedCell(robot, bus_cfg, sim, period_s, eds=eds)
        cell.start()
    except errs.DrivegainError as exc:
        conn.send(("error", type(exc).__name__, str(exc)))
        return
    except Exception as exc:
        conn.send(("error", "DriveError", f"the simulated cell failed to start: {exc!r}"))
        return
    # for the child's life, after the cell is built (its objects are then frozen too): its
    # drives must answer within the master's time-outs
    realtime = ExitStack()
    try:
        realtime.enter_context(policy.process())
    except OSError as exc:  # a CPU set the machine does not have
        cell.stop()
        conn.send(("error", "DriveError", f"the simulated drives' realtime policy: {exc}"))
        return
    parent_gone = False
    try:
        conn.send(("ready", None, None))
        while True:
            if conn.poll(_POLL_S):
                conn.recv()  # "stop"; EOFError when the parent is gone
                break
    except (EOFError, OSError):
        parent_gone = True
    finally:
        if parent_gone:
            _outlive_master(cell)
        cell.stop()
        realtime.close()
    try:
        conn.send(("stopped", cell.errors, cell.fault_log()))
    except (OSError, EOFError):
        pass


def _outlive_master(cell: SimulatedCell) -> None:
    """The master is gone: serve until the drives that watch its heartbeat have stopped the
    robot (every motor braked), at most :data:`OUTLIVE_S`; log what happened."""
    log = logging.getLogger(__name__)
    watching = [d for d in cell.drives.values() if d.consumer.active]
    log.warning(
        "simulated drives: the master is gone; %d of %d drives watch its heartbeat",
        len(watching),
        len(cell.drives),
    )
    deadline = time.monotonic() + OUTLIVE_S
    while watching and time.monotonic() < deadline:
        with cell.locked():
            powered = cell.physics.any_powered
        if not powered:
            break
        time.sleep(0.05)
    with cell.locked():
        speed = float(abs(cell.physics.qd).max())
        states = sorted({d.state.name for d in cell.drives.values()})
    log.warning(
        "simulated drives: robot %s after the master left (largest joint speed %.3g rad/s, "
        "drives %s)",
        "at rest" if speed == 0.0 else "still moving",
        speed,
        ", ".join(states),
    )


def main(argv: list[str]) -> int:
    """Child entry point: ``python -m drivegain.drivers.simprocess FD``."""
    conn = Connection(int(argv[1]))
    try:
        robot, bus_cfg, sim, period_s, eds, policy = conn.recv()
    except (EOFError, OSError):
        return 1
    _serve(robot, bus_cfg, sim, period_s, eds, policy, conn)
    return 0


def _error(kind: str, message: str) -> errs.DrivegainError:
    cls = getattr(errs, kind, None)
    if isinstance(cls, type) and issubclass(cls, errs.DrivegainError):
        try:
            return cls(message)
        except TypeError:
            pass
    return DriveError(message)


class SimulatedCellProcess(Running):
    """A :class:`~drivegain.drivers.sim.SimulatedCell` served from a child process.

    Parameters
    ----------
    robot, sim, period_s, eds
        As for :class:`~drivegain.drivers.sim.SimulatedCell`.
    bus_cfg
        The master's bus: ``interface = "drivegain-ipc"``, ``channel`` the socket path (the
        child opens it as the server); or ``socketcan`` on a vcan device with a ``realtime``
        simulation (the child opens a socket of its own on the device, ``[bus.options]``
        included).
    policy
        The realtime policy whose process part the child enters for its life (default: the
        garbage-collector freeze only); its cycle-thread part does not apply (no cycle loop).

    Use as a context manager, or :meth:`start` then :meth:`stop` (which never raises).
    ``errors`` and :meth:`fault_log` are filled when the child has stopped.
    """

    def __init__(
        self,
        robot: Robot,
        bus_cfg: BusConfig,
        sim: SimConfig,
        period_s: float,
        *,
        eds: Path | None = None,
        policy: RealtimePolicy | None = None,
    ):
        if not drives_in_child_process(bus_cfg, sim):
            raise ConfigError(
                f"a simulated cell in its own process needs the {INTERFACE} interface, or "
                f"{SOCKETCAN} with a realtime simulation, not {bus_cfg.interface} with "
                f"{sim.clock}: lockstep shares its simulated clock within one process only"
            )
        self.robot = robot
        if bus_cfg.interface == INTERFACE:
            bus_cfg = BusConfig(
                interface=INTERFACE,
                channel=bus_cfg.channel,
                bitrate=bus_cfg.bitrate,
                extra={**bus_cfg.extra, "role": "server"},
            )
        self.bus_cfg = bus_cfg
        self.sim = sim
        self.period_s = period_s
        self.eds = eds
        self.policy = policy if policy is not None else RealtimePolicy()
        self._conn: Connection | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._errors: list[str] = []
        self._faults: list[FaultRecord] = []

    @property
    def pid(self) -> int | None:
        """Process id of the child while it runs."""
        return self._proc.pid if self._proc is not None else None

    def start(self) -> None:
        """Start the child and wait until its drives are on the bus.

        Raises
        ------
        ConfigError, DriveError, BusError
            As :class:`SimulatedCell` would raise them; DriveError if the child does not come up
            within :data:`START_TIMEOUT_S`.
        """
        if self._proc is not None:
            raise DriveError("the simulated cell is already started")
        mine, theirs = socket.socketpair()
        with theirs:
            proc = subprocess.Popen(
                [sys.executable, "-m", "drivegain.drivers.simprocess", str(theirs.fileno())],
                pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL,
            )
        conn = Connection(mine.detach())
        self._proc, self._conn = proc, conn
        RUNNING.add(self)
        try:
            conn.send((self.robot, self.bus_cfg, self.sim, self.period_s, self.eds, self.policy))
            if not conn.poll(START_TIMEOUT_S):
                raise DriveError(
                    f"the simulated cell process did not start within {START_TIMEOUT_S:g} s"
                )
            kind, a, b = conn.recv()
        except (EOFError, OSError):
            self.stop()
            raise DriveError(
                f"the simulated cell process exited during start-up (exit code {proc.returncode})"
            ) from None
        except BaseException:
            self.stop()
            raise
        if kind == "error":
            self.stop()
            raise _error(a, b)

    def stop(self) -> None:
        """Tell the child to stop, collect its report, reap it (never raises)."""
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        if conn is not None:
            try:
                conn.send("stop")
                if conn.poll(STOP_TIMEOUT_S):
                    kind, errors, faults = conn.recv()
                    if kind == "stopped":
                        self._errors, self._faults = errors, faults
            except (OSError, EOFError, ValueError):
                pass
            conn.close()
        if proc is not None:
            try:
                proc.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        RUNNING.discard(self)

    @property
    def errors(self) -> list[str]:
        """Exceptions raised in the child's bus callbacks (known once it has stopped)."""
        return list(self._errors)

    def fault_log(self) -> list[FaultRecord]:
        """Injected faults that took effect (known once the child has stopped)."""
        return list(self._faults)


if __name__ == "__main__":
    sys.exit(main(sys.argv))
