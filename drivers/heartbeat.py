"""The master's own heartbeat (CiA 301 §7.2.8.3.2.2): what tells the drives that drivegain lives.

Each drive's heartbeat consumer (0x1016) watches it: a drive that misses it for its consumer
time goes to its fault reaction (quick stop, then disable, EMCY 0x8130), so the robot stops when
drivegain dies, whatever killed it. The master sends COB-ID 0x700 + its node id with one data
byte, its NMT state (0x05, operational), every period:

- on the wall clock, from a thread of its own, so that a busy cycle thread or a stalled caller
  does not silence it while the process is alive;
- in lockstep, as a periodic action of the simulated clock (:mod:`.simtime`), so that the
  drives' consumer counts simulated time like every other time-out.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import canopen

from drivegain.drivers.simtime import LockstepClock, TimeBase
from drivegain.errors import ConfigError

logger = logging.getLogger(__name__)

#: The master's NMT state in its heartbeat: operational.
NMT_OPERATIONAL = 0x05
#: Default node id of the master: the highest, which drives leave free by convention.
DEFAULT_MASTER_NODE_ID = 127
#: Default period of the master's heartbeat, s.
DEFAULT_MASTER_HEARTBEAT_S = 0.1
#: The drives' consumer time-out, in master heartbeat periods.
CONSUMER_PERIODS = 3


@dataclass(frozen=True)
class MasterHeartbeat:
    """The master's heartbeat and the drives' consumer of it.

    Attributes
    ----------
    node_id
        The master's node id, 1..127 (no drive may have it).
    period_s
        Heartbeat period, s (0.001..65.535 / :data:`CONSUMER_PERIODS`, whole ms).
    """

    node_id: int = DEFAULT_MASTER_NODE_ID
    period_s: float = DEFAULT_MASTER_HEARTBEAT_S

    def __post_init__(self) -> None:
        if not 1 <= self.node_id <= 127:
            raise ConfigError(f"master node id must be 1..127, got {self.node_id}")
        if not 1 <= round(self.period_s * 1000) * CONSUMER_PERIODS <= 0xFFFF:
            raise ConfigError(f"master heartbeat period {self.period_s} s is out of range")

    @property
    def cob_id(self) -> int:
        """COB-ID of the heartbeat frame."""
        return 0x700 + self.node_id

    @property
    def consumer_ms(self) -> int:
        """The drives' consumer time-out, ms (:data:`CONSUMER_PERIODS` periods)."""
        return round(self.period_s * 1000) * CONSUMER_PERIODS

    @property
    def consumer_entry(self) -> int:
        """0x1016 sub 1: producer node id in bits 16-23, consumer time (ms) in bits 0-15."""
        return self.node_id << 16 | self.consumer_ms


class HeartbeatProducer:
    """Sends the master's heartbeat every period while running.

    Parameters
    ----------
    network
        The connected network to send on.
    heartbeat
        Node id and period.
    clock
        The master's clock: on a :class:`~.simtime.LockstepClock` the heartbeat is a periodic
        action of simulated time, otherwise a thread sends it on the wall clock.
    """

    def __init__(self, network: canopen.Network, heartbeat: MasterHeartbeat, clock: TimeBase):
        self.network = network
        self.heartbeat = heartbeat
        self.clock = clock
        self._generation = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def running(self) -> bool:
        return self._generation > 0 and not self._stop.is_set()

    def start(self) -> None:
        """Start producing (no-op if running): the first heartbeat leaves at once."""
        if self.running:
            return
        self._stop.clear()
        self._generation += 1
        self._send()
        if isinstance(self.clock, LockstepClock):
            self._schedule(self.clock, self._generation, self.clock.now())
        else:
            self._thread = threading.Thread(
                target=self._run, name="drivegain-master-heartbeat", daemon=True
            )
            self._thread.start()

    def stop(self) -> None:
        """Stop producing (the drives' consumers then time out unless told otherwise)."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(2.0)

    def _send(self) -> None:
        try:
            self.network.send_message(self.heartbeat.cob_id, bytes([NMT_OPERATIONAL]))
        except Exception as exc:  # the supervisor reports a failing bus; keep producing
            logger.warning("master heartbeat not sent: %s", exc)

    def _schedule(self, clock: LockstepClock, generation: int, last: float) -> None:
        due = last + self.heartbeat.period_s

        def beat() -> None:
            if self._stop.is_set() or generation != self._generation:
                return
            self._send()
            self._schedule(clock, generation, due)

        clock.call_at(due, beat)

    def _run(self) -> None:
        period = self.heartbeat.period_s
        due = time.monotonic() + period
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            self._send()
            due += period
            now = time.monotonic()
            if due < now:  # a stalled process: keep the period, do not send a burst
                due = now + period
