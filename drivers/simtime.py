"""Which clock the supervision reads: the wall clock, or the simulated clock of lockstep.

A master and the simulated drives it talks to in lockstep share one :class:`LockstepClock`
(both on python-can's in-process ``virtual`` bus). Simulated time then advances in two ways
only:

- by one period per SYNC (the drives' SYNC handler calls :meth:`LockstepClock.sync_instant`);
- while a party waits for something that cannot come any more: when every frame sent so far has
  been handled by its receiver (the clock counts the frames each side sends and handles), nothing
  is in flight, so simulated time jumps to the next scheduled action (a heartbeat, a late TPDO)
  or to the end of the wait, whichever comes first.

Every supervision time-out (heartbeat consumers on both sides, TPDO time-out, boot and state
waits) therefore counts simulated time: a run has the same outcome on a quiet and on a saturated
machine. The wall clock only bounds a real hang (:data:`HANG_S`): a wait during which nothing
moves for that long raises a :class:`~drivegain.errors.DriveError` naming what hung.

When one side leaves (a master closed or dead, drives powered off), nobody can advance the clock
for it: the clock then follows the wall clock from where it stood (:meth:`LockstepClock.detach`),
so the remaining side's consumer still fires, and its scheduled actions run from a thread of the
clock. Frames carry the simulated time they were sent at (``msg.timestamp``), so a heartbeat is
stamped with its simulated instant whatever the receiving thread's delay.

On python-can's ``virtual`` bus a frame between the two sides skips the bus's queue and reader
thread: the sender's thread hands it to the receiver's listeners as soon as it lets go of its
network's send lock, in the order frames were sent, the receiver's own answers included. A SYNC
cycle (RPDOs, SYNC, the drives' SYNC handling and physics, the TPDOs back to the master) then
runs in the master's thread with no thread hand-off, the same steps the reader threads took. Any
other bus on the channel (a CAN trace) gets every frame through its queue as before.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

import can
from can.interfaces.virtual import VirtualBus

from drivegain.errors import DriveError

logger = logging.getLogger(__name__)

#: Wall-clock seconds a lockstep wait may see no progress at all before it is called a hang.
HANG_S = 30.0
#: Wall-clock slice a lockstep wait sleeps while frames are in flight, s.
_POLL_S = 0.0005

#: Scheduled actions, a heap of (due time in s, sequence number, action).
Schedule = list[tuple[float, int, Callable[[], None]]]


def wait_until_due(
    cond: threading.Condition,
    heap: Schedule,
    now: Callable[[], float],
    stopped: Callable[[], bool],
) -> bool:
    """With ``cond`` held, wait until the earliest action of ``heap`` is due.

    Parameters
    ----------
    cond
        The condition notified when ``heap`` changes or the timer stops (held by the caller).
    heap
        The scheduled actions.
    now
        The timer's clock, s.
    stopped
        Whether the timer was stopped.

    Returns
    -------
    bool
        True when an action is due (still on the heap), False once the timer is stopped.
    """
    while not stopped():
        t = now()
        if heap and heap[0][0] <= t:
            return True
        cond.wait(heap[0][0] - t if heap else None)
    return False


class Flag(Protocol):
    """What a wait waits for (a :class:`threading.Event`)."""

    def is_set(self) -> bool: ...

    def wait(self, timeout: float | None = None) -> bool: ...


class TimeBase(Protocol):
    """The clock of a master's supervision (seconds, any origin)."""

    @property
    def simulated(self) -> bool:
        """True for lockstep's simulated clock."""
        ...

    def now(self) -> float:
        """The present, s."""
        ...

    def stamp(self, msg: can.Message) -> float:
        """When ``msg`` was sent, on this clock, s (called at reception)."""
        ...

    def wait(self, flag: Flag, timeout_s: float, what: str) -> bool:
        """Wait until ``flag`` is set (True) or ``timeout_s`` of this clock passed (False)."""
        ...

    def sleep(self, seconds: float, what: str) -> None:
        """Let ``seconds`` of this clock pass."""
        ...

    def sync_time(self, sent: float) -> float:
        """The instant of the SYNC last sent (``sent``: :meth:`now` when it was sent), s."""
        ...


class WallTime:
    """The wall clock (``time.monotonic``): realtime runs and hardware."""

    simulated = False

    def now(self) -> float:
        return time.monotonic()

    def stamp(self, msg: can.Message) -> float:
        return time.monotonic()

    def wait(self, flag: Flag, timeout_s: float, what: str) -> bool:
        return flag.wait(max(0.0, timeout_s))

    def sleep(self, seconds: float, what: str) -> None:
        time.sleep(max(0.0, seconds))

    def sync_time(self, sent: float) -> float:
        return sent


class _Never:
    """A flag that is never set (for :meth:`LockstepClock.sleep`)."""

    def is_set(self) -> bool:
        return False

    def wait(self, timeout: float | None = None) -> bool:
        if timeout:
            time.sleep(timeout)
        return False


class _Party:
    """One side of the bus (the master's network or the simulated drives'): frames it sent and
    frames it has finished handling; on the in-process virtual bus, its receive queue and the
    listeners a frame delivered directly goes to."""

    def __init__(self, name: str, inbox: Any = None, notifier: Any = None):
        self.name = name
        self.sent = 0
        self.handled = 0
        self.inbox = inbox  # the virtual bus's receive queue (None: another bus)
        self.notifier = notifier

    def receive(self, msg: can.Message) -> None:
        """Hand ``msg`` to this side's listeners, as its bus reader thread would."""
        for listener in list(self.notifier.listeners):
            try:
                listener(msg)
            except Exception:  # as the reader thread would, go on with the next frames
                logger.exception("lockstep bus: a listener of %s failed", self.name)


class _PostingLock:
    """A network's send lock whose release delivers the frames sent meanwhile (lockstep on the
    virtual bus: :meth:`LockstepClock._deliver`).

    Delivery waits for the release because a receiver may send in turn on the same network (a
    SYNC handled by the drives advances the clock, which may fire the master's heartbeat):
    canopen's send lock is not re-entrant.
    """

    def __init__(self, clock: LockstepClock):
        self._lock = threading.Lock()
        self._clock = clock

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        return self._lock.acquire(blocking, timeout)

    def release(self) -> None:
        self._lock.release()
        self._clock._deliver()

    def locked(self) -> bool:
        return self._lock.locked()

    def __enter__(self) -> bool:
        return self._lock.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


class _Counter(can.Listener):
    """Last listener of a party's notifier: a frame counts as handled once every listener before
    it has run."""

    def __init__(self, clock: LockstepClock, party: _Party):
        self.clock = clock
        self.party = party

    def on_message_received(self, msg: can.Message) -> None:
        with self.clock._lock:  # (nobody waits for a count: a wait polls, see LockstepClock.wait)
            self.party.handled += 1

    def stop(self) -> None:
        """Nothing to release."""


def _virtual_send(
    bus: Any, post: Callable[[Any, can.Message], bool]
) -> Callable[[can.Message, float | None], None] | None:
    """What python-can's virtual bus does to send a frame, copying it by its constructor; a frame
    for a receive queue that ``post`` takes (a party of the lockstep clock: delivered directly,
    see :meth:`LockstepClock._post`) skips the queue and the copy.

    ``VirtualBus.send`` copies each frame with ``copy.deepcopy``, the costliest step of a frame on
    the in-process bus (more than the rest of sending it together). The copy here has the same
    fields; its time stamp is the sender's, as with ``preserve_timestamps``. ``None`` for another
    bus, or a virtual bus whose internals this does not know.
    """
    if not isinstance(bus, VirtualBus) or not all(
        hasattr(bus, a) for a in ("channel", "queue", "channel_id", "receive_own_messages")
    ):
        return None
    message = can.Message
    channel_id = bus.channel_id

    def send(msg: can.Message, timeout: float | None = None) -> None:
        bus._check_if_open()
        all_sent = True
        own = bus.queue
        for bus_queue in bus.channel:
            if bus_queue is own and not bus.receive_own_messages:
                continue
            # a party's listeners get the sent frame itself, marked received as a copy would
            # be: every sender here makes a new frame per send (canopen's send_message, the
            # simulated cell) and never changes it after (copies below set those two fields)
            if bus_queue is not own and post(bus_queue, msg):
                msg.channel, msg.is_rx = channel_id, True
                continue
            copy = message(
                timestamp=msg.timestamp,
                arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id,
                is_remote_frame=msg.is_remote_frame,
                is_error_frame=msg.is_error_frame,
                channel=channel_id,
                dlc=msg.dlc,
                data=bytearray(msg.data),
                is_fd=msg.is_fd,
                is_rx=bus_queue is not own,
                bitrate_switch=msg.bitrate_switch,
                error_state_indicator=msg.error_state_indicator,
            )
            try:
                bus_queue.put(copy, block=True, timeout=timeout)
            except queue.Full:
                all_sent = False
        if not all_sent:
            raise can.CanOperationError("Could not send message to one or more recipients")

    return send


class LockstepClock:
    """Simulated time shared by a master and its simulated drives in one process.

    Parameters
    ----------
    hang_s
        Wall-clock seconds without progress that make a wait a hang.
    """

    simulated = True

    def __init__(self, hang_s: float = HANG_S):
        self.hang_s = hang_s
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._advance = threading.RLock()  # actions fire in time order, one thread at a time
        self._now = 0.0
        self._last_sync = 0.0  # the first SYNC is one period after power-on, as before any jump
        self._heap: Schedule = []
        self._seq = itertools.count()
        self._parties: list[_Party] = []
        self._met = False  # two parties were attached at once
        self._free_since: float | None = None  # wall time the clock started following the wall
        self._free_thread: threading.Thread | None = None
        self._closed = False
        # Direct delivery on the virtual bus: frames for a party, in the order they were sent,
        # and the thread handing them to their receivers now (one at a time, as a reader would).
        self._mail: deque[tuple[_Party, can.Message]] = deque()
        self._mail_lock = threading.Lock()
        self._courier: int | None = None
        self._inboxes: dict[int, _Party] = {}  # id(receive queue) -> attached party

    # --- time ------------------------------------------------------------------------------
    def now(self) -> float:
        """Simulated time, s (follows the wall clock once a side has left)."""
        with self._lock:
            if self._free_since is not None:
                return self._now + time.monotonic() - self._free_since
            return self._now

    def stamp(self, msg: can.Message) -> float:
        """The simulated instant ``msg`` was sent (its sender stamped it; a frame of a bus that
        is no party of this clock carries a wall-clock stamp, later than any simulated one: it
        counts as sent now)."""
        return min(float(msg.timestamp), self.now())

    @property
    def free_running(self) -> bool:
        """A side has left: the clock follows the wall clock."""
        return self._free_since is not None

    def sync_instant(self, period_s: float, step_s: float) -> float:
        """Advance to the instant of a SYNC just received and return it, s.

        One period after the previous SYNC, or now if a wait already went past that; rounded up
        to the simulation step ``step_s``. Actions due until then run first.
        """
        with self._lock:
            t = max(self._last_sync + period_s, self.now())
            t = math.ceil(t / step_s - 1e-6) * step_s
            self._last_sync = t
        self.advance_to(t)
        return t

    def call_at(self, t: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` when simulated time reaches ``t`` (in the thread that advances it)."""
        with self._lock:
            heapq.heappush(self._heap, (t, next(self._seq), fn))
            self._changed.notify_all()

    def advance_to(self, t: float) -> None:
        """Run every action due by ``t`` in time order, then stand at ``t`` (never goes back)."""
        with self._advance:
            while True:
                with self._lock:
                    if not self._heap or self._heap[0][0] > t:
                        if self._free_since is None:
                            self._now = max(self._now, t)
                        return
                    due, _, fn = heapq.heappop(self._heap)
                    if self._free_since is None:
                        self._now = max(self._now, due)
                fn()

    # --- the two sides ---------------------------------------------------------------------
    def attach(self, network: Any, name: str) -> None:
        """Count the frames ``network`` (a connected :class:`canopen.Network`) sends and handles,
        and stamp the frames it sends with simulated time. Call it once the network's own
        listeners are in place: the counter must be its notifier's last listener."""
        bus, notifier = network.bus, network.notifier
        virtual = _virtual_send(bus, self._post)
        party = _Party(name, bus.queue if virtual else None, notifier)
        send, shutdown = virtual or bus.send, bus.shutdown
        # the virtual bus overwrites a frame's time stamp unless told to keep it
        bus.preserve_timestamps = True
        if virtual is not None:
            # frames are delivered when the sender lets go of its network's send lock
            network.send_lock = _PostingLock(self)

        def counted_send(msg: can.Message, timeout: float | None = None) -> None:
            with self._lock:
                msg.timestamp = self._now if self._free_since is None else self.now()
                party.sent += 1
            send(msg, timeout)

        def detaching_shutdown() -> None:
            self.detach(name)
            shutdown()

        bus.send = counted_send
        bus.shutdown = detaching_shutdown
        notifier.add_listener(_Counter(self, party))
        with self._lock:
            self._parties.append(party)
            if party.inbox is not None:
                with self._mail_lock:
                    self._inboxes[id(party.inbox)] = party
            if len(self._parties) == 2:
                self._met = True
                for p in self._parties:  # frames sent before both listened reached nobody
                    p.sent = p.handled = 0

    def detach(self, name: str) -> None:
        """Side ``name`` left: from now on the clock follows the wall clock (the other side's
        consumer must still see it go), and its own actions run from the clock's thread."""
        with self._lock:
            self._parties = [p for p in self._parties if p.name != name]
            with self._mail_lock:  # its bus reader thread gets what is sent to it from now on
                self._inboxes = {k: p for k, p in self._inboxes.items() if p.name != name}
            if not self._met or self._free_since is not None:
                return
            self._free_since = time.monotonic()
            self._changed.notify_all()
            if self._parties:
                self._free_thread = threading.Thread(
                    target=self._run_free, name="drivegain-lockstep-clock", daemon=True
                )
                self._free_thread.start()

    def close(self) -> None:
        """Stop the clock's thread (the drives stopped)."""
        with self._lock:
            self._closed = True
            self._heap.clear()
            self._changed.notify_all()
        thread = self._free_thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(2.0)

    def _run_free(self) -> None:
        while True:
            with self._lock:
                if not wait_until_due(self._changed, self._heap, self.now, lambda: self._closed):
                    return
            self.advance_to(self.now())

    # --- direct delivery (virtual bus) -------------------------------------------------------
    def _post(self, inbox: Any, msg: can.Message) -> bool:
        """Queue ``msg`` for the party whose receive queue is ``inbox``; False if no party of
        this clock reads it (the frame then takes the queue, to that bus's reader thread)."""
        with self._mail_lock:
            party = self._inboxes.get(id(inbox))
            if party is None:
                return False
            self._mail.append((party, msg))
            return True

    def _deliver(self) -> None:
        """Hand the queued frames to their receivers' listeners in this thread, in the order they
        were sent, including those the receivers send meanwhile; does nothing if another thread
        (or this one, further up its stack) is delivering: that one takes the new frames too.

        In lockstep a frame's effect then needs no thread hand-off (bus reader threads woken,
        the interpreter lock passed back and forth): a SYNC cycle runs in the sender's thread.
        What happens is what the reader threads did, in the same order per receiver; the time
        stamps are simulated time, so the outcome does not depend on which thread delivers.
        """
        with self._mail_lock:
            if self._courier is not None or not self._mail:
                return
            self._courier = threading.get_ident()
        try:
            while True:
                with self._mail_lock:
                    if not self._mail:  # (with the check: a frame posted now finds no courier)
                        self._courier = None
                        return
                    party, msg = self._mail.popleft()
                party.receive(msg)
        except BaseException:
            with self._mail_lock:
                self._courier = None
            raise

    def settled(self) -> bool:
        """Every frame sent has been handled by the other side: nothing is in flight."""
        with self._lock:
            if len(self._parties) < 2:
                return True
            a, b = self._parties[0], self._parties[1]
            return b.handled >= a.sent and a.handled >= b.sent

    # --- waits -----------------------------------------------------------------------------
    def wait(self, flag: Flag, timeout_s: float, what: str) -> bool:
        """Wait until ``flag`` is set (True) or ``timeout_s`` simulated seconds passed (False).

        Raises
        ------
        DriveError
            Nothing moved (no frame handled, no simulated time passed) for :attr:`hang_s`
            wall-clock seconds: the simulation hung while waiting for ``what``.
        """
        # The wait counts from when what the caller sent has been handled (the SYNC it waits
        # the answer of has advanced the clock), not from when this thread got here: the same
        # instant however late either thread runs.
        deadline: float | None = None
        progress = time.monotonic()
        seen = self._progress()
        while True:
            self._deliver()  # frames sent without the send lock, if any
            if flag.is_set():
                return True
            if self.free_running:
                if deadline is None:
                    deadline = self.now() + max(0.0, timeout_s)
                left = deadline - self.now()
                if left <= 0.0:
                    return bool(flag.is_set())
                flag.wait(min(left, 0.01))
                continue
            if self.settled():
                # the flag is set before the frame that set it counts as handled: once settled,
                # this look at it is final (without it, a frame handled since the first look
                # would let simulated time jump although the wait is over)
                if flag.is_set():
                    return True
                if deadline is None:
                    deadline = self.now() + max(0.0, timeout_s)
                with self._lock:
                    nxt = self._heap[0][0] if self._heap else math.inf
                if nxt <= deadline:
                    self.advance_to(nxt)
                    progress = time.monotonic()
                    continue
                self.advance_to(deadline)
                return bool(flag.is_set())
            flag.wait(_POLL_S)
            now_seen = self._progress()
            if now_seen != seen:
                seen, progress = now_seen, time.monotonic()
            elif time.monotonic() - progress > self.hang_s:
                raise DriveError(
                    f"lockstep simulation hung: waiting for {what}, no frame was handled and no "
                    f"simulated time passed for {self.hang_s:g} s of wall-clock time"
                )

    def sleep(self, seconds: float, what: str) -> None:
        """Let ``seconds`` of simulated time pass (actions due meanwhile run)."""
        self.wait(_Never(), seconds, what)

    def sync_time(self, sent: float) -> float:
        """The instant the drives handled the last SYNC at, s."""
        with self._lock:
            return self._last_sync

    def _progress(self) -> tuple[int, ...]:
        with self._lock:
            return tuple(x for p in self._parties for x in (p.sent, p.handled))
