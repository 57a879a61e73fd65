"""The master side: CiA 402 drives in cyclic synchronous position mode over CANopen.

One :class:`Master` drives every joint of a robot through canopen ``RemoteNode``s on a connected
:class:`canopen.Network`. It does not care whether the drives are real or simulated: the bus
configuration is the only difference.

The master is a facade over one part per job, sharing the per-drive records of :mod:`.link`:

- :mod:`.configure`: SDO configuration and PDO mapping of each drive (canopen's PDO maps);
- :mod:`.statewalk`: the CiA 402 state walk by SDO;
- :mod:`.exchange`: RPDOs, SYNC, TPDO collection tagged by SYNC counter, :class:`CycleSample`;
- :mod:`.supervisor`: heartbeat consumer, EMCY, CAN error frames, faults and events;
- :mod:`.heartbeat`: the master's own heartbeat, which the drives' consumers (0x1016) watch.

Time-outs count the master's clock (:mod:`.simtime`): the wall clock, or in lockstep the
simulated clock the master shares with the simulated drives.

Here: NMT, the public sequence (boot, enable, cycle, quick stop, disable, close) and frame
dispatch. Reception does not use canopen's per-id callbacks (one failing callback silently skips
the others, error frames are dropped, the EMCY log grows without bound, there is no heartbeat
time-out). The master adds one :class:`can.Listener` to the network's notifier instead, which
sees every frame: TPDOs go to the exchanger, heartbeats, EMCYs and error frames to the
supervisor. Faults noticed there are raised by the next :meth:`Master.cycle` or
:meth:`Master.check` in the caller's thread, as :class:`DriveError`.

Two cyclic exchanges (docs/realtime.md): :meth:`Master.cycle` (same cycle: SYNC k, then cycle k's
TPDOs; lockstep) and :meth:`Master.cycle_pipelined` (SYNC k, then the TPDOs of cycle k−1, which
had a whole period to arrive; realtime). Reaction time of the pipelined supervision, T the
period: faults of the notifier thread (EMCY, heartbeat, NMT, bus) are raised before the next
SYNC as in the same cycle exchange; what cycle k's TPDOs show (statusword fault, a missing TPDO,
the positions the session supervises) is raised by the call that sends SYNC k+1, one period
later, a missing TPDO at max(T, ``tpdo_s``) after SYNC k instead of ``tpdo_s``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import canopen
import numpy as np
from canopen.objectdictionary import ObjectDictionary

from drivegain.config.robot import Robot
from drivegain.drivers import objects as ob
from drivegain.drivers.bus import BusLoad
from drivegain.drivers.cia402 import POWERED, Command, State
from drivegain.drivers.configure import DriveConfigurator
from drivegain.drivers.exchange import (
    CycleExchanger,
    CycleSample,
    FrameDispatcher,
    PipelinedCycle,
    SyncSent,
)
from drivegain.drivers.heartbeat import HeartbeatProducer, MasterHeartbeat
from drivegain.drivers.link import DriveLink, Timeouts, sdo_read, sdo_write, send
from drivegain.drivers.simtime import HANG_S, LockstepClock, TimeBase, WallTime
from drivegain.drivers.statewalk import StateWalker
from drivegain.drivers.supervisor import ERROR_FRAMES_PER_S, DriveEvent, Supervisor
from drivegain.errors import BusError, ConfigError, DriveError, UsageError
from drivegain.formats.log import EventLevel
from drivegain.lifecycle import Closing

__all__ = [
    "ERROR_FRAMES_PER_S",
    "CycleSample",
    "DriveEvent",
    "Master",
    "MasterHeartbeat",
    "PipelinedCycle",
    "SyncSent",
    "Timeouts",
]

logger = logging.getLogger(__name__)

#: NMT commands (CiA 301 §7.2.8.3.1), sent to COB-ID 0x000 with the node id.
_NMT_START = 0x01
_NMT_PRE_OPERATIONAL = 0x80
_NMT_RESET_COMMUNICATION = 0x82


class Master(Closing):
    """CiA 402 drives of one robot, cyclic synchronous position.

    Parameters
    ----------
    robot
        The robot: joint order, node ids, gear ratios, couplings, encoder counts.
    network
        A connected network (see :func:`drivegain.drivers.bus.open_network`); the caller
        disconnects it after :meth:`close`.
    period_s
        SYNC period, s (written to the drives as interpolation period 0x60C2).
    eds
        The drives' EDS (default: the shipped ``cia402-servo.eds``). The master uses only
        standard CiA 301/402 objects, plus the SYNC echo 0x2010 if the EDS has it.
    timeouts
        Time limits.
    heartbeat
        The master's own heartbeat (node id, period), which every drive's consumer (0x1016)
        is set to watch; default :class:`~.heartbeat.MasterHeartbeat`.
    clock
        The clock the time limits count: the wall clock (default), or the
        :class:`~.simtime.LockstepClock` of simulated drives in lockstep, which the master then
        joins (SDO answers of simulated drives take no simulated time: their wait is bounded by
        the clock's hang limit only).

    Raises
    ------
    BusError
        The network is not connected.
    ConfigError
        The period cannot be written to the drives, the EDS is unreadable or lacks an object
        the master uses, or a drive has the master's node id.
    """

    def __init__(
        self,
        robot: Robot,
        network: canopen.Network,
        *,
        period_s: float,
        eds: Path | None = None,
        timeouts: Timeouts | None = None,
        heartbeat: MasterHeartbeat | None = None,
        clock: TimeBase | None = None,
    ):
        if network.notifier is None or network.bus is None:
            raise BusError("the CANopen network is not connected")
        interpolation = ob.interpolation_period(period_s)
        self.heartbeat = heartbeat or MasterHeartbeat()
        if self.heartbeat.node_id in robot.node_ids:
            raise ConfigError(
                f"the master's node id {self.heartbeat.node_id} is a drive's node id",
                file=robot.source,
            )
        self.clock: TimeBase = clock or WallTime()
        self.robot = robot
        self.network = network
        self.period_s = period_s
        self.timeouts = timeouts or Timeouts()
        self.eds = Path(eds) if eds is not None else ob.default_eds()
        self._drives: list[DriveLink] = []
        od_probe: ObjectDictionary | None = None
        for j, joint in enumerate(robot.joints):
            try:
                od = ob.load_od(self.eds, joint.node_id)
            except Exception as exc:
                raise ConfigError(f"cannot read the EDS ({exc})", file=self.eds) from None
            od_probe = od_probe or od
            node = canopen.RemoteNode(joint.node_id, od)
            node.sdo.RESPONSE_TIMEOUT = (
                max(self.timeouts.sdo_s, HANG_S) if self.clock.simulated else self.timeouts.sdo_s
            )
            self._drives.append(
                DriveLink(
                    joint=j,
                    node_id=joint.node_id,
                    node=node,
                    cpr=ob.counts_per_radian(joint.encoder_counts),
                    rated_a=joint.rated_current,
                )
            )
        assert od_probe is not None  # a robot file has at least one joint
        # SYNC carries a counter only if the drives know its overflow value (0x1019); otherwise
        # they may reject it ("unexpected SYNC data length").
        sync_counter = ob.SYNC_OVERFLOW in od_probe
        echo = od_probe.get(ob.SYNC_ECHO)
        tagged = sync_counter and echo is not None and getattr(echo, "pdo_mappable", False)
        self.layout = ob.TAGGED_LAYOUT if tagged else ob.PLAIN_LAYOUT
        self._supervisor = Supervisor(self._drives, network, self.timeouts, self.clock)
        self._configurator = DriveConfigurator(
            robot,
            od_probe,
            self.eds,
            self.layout,
            sync_counter=sync_counter,
            heartbeat_ms=round(self.timeouts.heartbeat_producer_s * 1000),
            consumer=self.heartbeat.consumer_entry,
            interpolation=interpolation,
            supervisor=self._supervisor,
        )
        self._walker = StateWalker(self._supervisor, self.timeouts)
        self._exchanger = CycleExchanger(
            self._drives,
            network,
            self.layout,
            robot.transmission(),
            sync_counter=sync_counter,
            timeouts=self.timeouts,
            supervisor=self._supervisor,
        )
        self._streaming = False
        self._staged_target = np.zeros(0)  # the target of stage(), rad
        self._booted = False
        self._closed = False
        # Nodes join the network only once the EDS passed the configurator's check: a refused
        # master leaves nothing behind.
        for d in self._drives:
            network.add_node(d.node)
        self._listener = FrameDispatcher(self._exchanger, self._supervisor, self.clock)
        network.notifier.add_listener(self._listener)
        self._producer = HeartbeatProducer(network, self.heartbeat, self.clock)
        if isinstance(self.clock, LockstepClock):
            self.clock.attach(network, "master")  # after the dispatcher: it counts handled frames

    # --- public API ----------------------------------------------------------------------------
    @property
    def node_ids(self) -> list[int]:
        """CANopen node ids, in joint order."""
        return [d.node_id for d in self._drives]

    @property
    def states(self) -> dict[int, State | None]:
        """Last CiA 402 state seen of each node."""
        return {d.node_id: d.state for d in self._drives}

    @property
    def cycle_index(self) -> int:
        """Index the next :meth:`cycle` will carry."""
        return self._exchanger.cycle

    @property
    def stale_frames(self) -> int:
        """TPDOs received outside their cycle (dropped)."""
        return self._exchanger.stale_frames

    def bus_load(self, bitrate: int) -> BusLoad:
        """Bus load of this master's cyclic exchange at ``bitrate``."""
        return self._exchanger.bus_load(self.period_s, bitrate)

    def boot(self) -> None:
        """NMT reset communication, boot-up, SDO configuration, NMT start.

        The master's heartbeat starts first; configuration per drive: see :mod:`.configure`
        (profile and CSP check, rated current, encoder resolution, PDO mapping, SYNC counter
        overflow, heartbeat producer, consumer of the master's heartbeat, interpolation period,
        mode of operation CSP).

        Raises
        ------
        DriveError
            A drive did not boot, refused a setting or is not a CSP-capable CiA 402 drive.
        ConfigError
            A drive disagrees with the robot file (encoder resolution).
        """
        sv = self._supervisor
        sv.monitoring = False
        self._streaming = False
        self._booted = False
        sv.clear_faults()
        for d in self._drives:
            sv.bootup[d.node_id].clear()
            sv.operational[d.node_id].clear()
        self._producer.start()
        for d in self._drives:
            send(self.network, 0x000, bytes([_NMT_RESET_COMMUNICATION, d.node_id]))
        sv.await_nmt(sv.bootup, "no boot-up message after NMT reset communication")
        for d in self._drives:
            self._configurator.configure(d)
        for d in self._drives:
            sv.operational[d.node_id].clear()
            send(self.network, 0x000, bytes([_NMT_START, d.node_id]))
        sv.await_nmt(sv.operational, "no OPERATIONAL heartbeat after NMT start")
        sv.start_consumer()
        self._booted = True
        sv.event(EventLevel.INFO, None, None, f"{len(self._drives)} drives booted and operational")

    def enable(self) -> None:
        """Bring every drive to OPERATION_ENABLED, holding its actual position.

        Faults are reset (rising edge of controlword bit 7), a quick stop is ended by "disable
        voltage"; then the target 0x607A is set to the actual position 0x6064 and the drive is
        walked through READY_TO_SWITCH_ON and SWITCHED_ON. Every transition has a time-out.

        Raises
        ------
        DriveError
            A transition timed out or a fault could not be reset.
        """
        self._require_booted()
        self._streaming = False
        self._supervisor.clear_faults()
        for d in self._drives:
            d.node.emcy.reset()  # canopen's own EMCY log, unused here, must not grow
        first = {d.node_id: self._walker.read_state(d) for d in self._drives}
        for d in self._drives:
            if first[d.node_id] in (
                State.FAULT,
                State.FAULT_REACTION_ACTIVE,
                State.QUICK_STOP_ACTIVE,
                State.NOT_READY_TO_SWITCH_ON,
            ):
                self._walker.walk(d, State.SWITCH_ON_DISABLED, first[d.node_id])
        for d in self._drives:
            counts = sdo_read(d, ob.POSITION_ACTUAL)
            sdo_write(d, ob.TARGET_POSITION, 0, counts)
            self._exchanger.targets[d.joint] = counts
        for d in self._drives:
            self._walker.walk(d, State.OPERATION_ENABLED)
        self._exchanger.abandon()  # a cycle of an earlier stream is not this one's
        self._exchanger.controlword = int(Command.ENABLE_OPERATION)
        self._streaming = True
        self._supervisor.event(EventLevel.INFO, None, None, "drives enabled (OPERATION_ENABLED)")

    def read_positions(self) -> np.ndarray:
        """Joint positions (rad) read by SDO from 0x6064."""
        self._require_booted()
        counts = np.array([sdo_read(d, ob.POSITION_ACTUAL) for d in self._drives])
        return self._exchanger.joint_positions(counts)

    def cycle(self, target: np.ndarray) -> CycleSample:
        """One SYNC cycle: RPDOs (target 0x607A + controlword), SYNC with counter, then wait for
        both TPDOs of every drive tagged with this SYNC.

        Parameters
        ----------
        target
            Joint positions to reach one period later, rad, (n,).

        Raises
        ------
        DriveError
            A drive faulted (statusword, EMCY), left OPERATION_ENABLED or CSP, went silent
            (heartbeat), or a TPDO of the cycle is missing (code 0x8250); node and code set.
        BusError
            Bus-off, error-passive or repeated error frames, or the interface failed.
        TrajectoryError
            ``target`` is not finite or outside the encoder range.
        """
        counts = self._streaming_targets(target)
        ex = self._exchanger
        if ex.in_flight is not None:
            self._drop_in_flight("a same-cycle exchange")
        ex.targets = counts
        sample = ex.exchange(ex.targets)
        ex.check_sample(sample)
        return sample

    def _streaming_targets(self, target: np.ndarray) -> np.ndarray:
        """Encoder counts of ``target`` once the drives are streaming and nothing is pending
        (the checks both cycle calls make before sending anything)."""
        self._require_booted()
        if not self._streaming:
            raise DriveError("the drives are not enabled (call enable() first)")
        self.check()
        return self._exchanger.target_counts(target)

    def stage(self, target: np.ndarray) -> None:
        """Send the RPDOs of the next :meth:`cycle_pipelined` now, ahead of its deadline.

        The drives hold synchronous RPDOs until the SYNC, so the next call, given the same
        ``target``, then sends the SYNC alone at its deadline: its timing no longer includes
        the RPDOs' sends. Only with the SYNC echo (:attr:`layout` tagged), where the previous
        cycle's TPDOs are taken after the SYNC; a quick stop or a disable forgets what was
        staged (the SYNCs they send carry RPDOs of their own).

        Raises
        ------
        DriveError
            As :meth:`cycle_pipelined` (a pending fault; nothing is sent).
        BusError
            The interface failed.
        TrajectoryError
            ``target`` is not finite or outside the encoder range (nothing sent).
        UsageError
            Without the SYNC echo.
        """
        if not self.layout.tagged:
            raise UsageError(
                "stage: without the SYNC echo the previous cycle's TPDOs are taken before the "
                "SYNC, so the RPDOs cannot go out ahead of it"
            )
        counts = self._streaming_targets(target)
        self._staged_target = np.array(target, dtype=float)
        self._exchanger.stage(counts)

    def cycle_pipelined(self, target: np.ndarray) -> PipelinedCycle:
        """One pipelined SYNC cycle: RPDOs (target 0x607A + controlword) and SYNC of cycle k,
        then the TPDOs of cycle k−1, checked as :meth:`cycle` checks its own.

        With the SYNC echo, cycle k−1's TPDOs are taken after SYNC k went out: they may come up
        to ``tpdo_s`` after their SYNC without delaying SYNC k. Without it, a cycle's TPDOs are
        those received before the next SYNC, so they are taken before SYNC k goes out (waiting,
        if one is not in yet, up to ``tpdo_s`` after their SYNC). After the last call,
        :meth:`collect_pending` takes the last cycle's TPDOs. After :meth:`stage` of the same
        ``target``, only the SYNC is sent.

        Parameters
        ----------
        target
            Joint positions to reach one period after SYNC k, rad, (n,).

        Returns
        -------
        PipelinedCycle
            SYNC k's times, and the sample of cycle k−1 (None on the first call of a stream).

        Raises
        ------
        DriveError
            As :meth:`cycle`; a fault shown by cycle k−1's TPDOs or a TPDO of cycle k−1 missing
            ``tpdo_s`` after its SYNC (code 0x8250) is raised after SYNC k went out.
        BusError
            As :meth:`cycle`.
        TrajectoryError
            ``target`` is not finite or outside the encoder range (nothing sent).
        """
        ex = self._exchanger
        if ex.staged is None:
            counts = self._streaming_targets(target)
        else:  # converted and checked by stage(); a fault since then still stops the SYNC
            if not np.array_equal(target, self._staged_target):
                raise UsageError("cycle_pipelined: not the target staged for this SYNC")
            self.check()
            counts = ex.staged
        previous = ex.in_flight
        sample: CycleSample | None = None
        if previous is not None and not self.layout.tagged:
            sample = ex.collect(previous)  # before the SYNC that would end its window
        ex.targets = counts
        flight = ex.send(counts)
        if previous is not None and self.layout.tagged:
            sample = ex.collect(previous)
        if sample is not None:
            ex.check_sample(sample)
        return PipelinedCycle(flight.sent, sample)

    def collect_pending(self) -> CycleSample | None:
        """The TPDOs of the cycle :meth:`cycle_pipelined` sent last (the end of a stream),
        checked as :meth:`cycle` checks its own; None if no cycle is in flight.

        Raises
        ------
        DriveError
            As :meth:`cycle`.
        BusError
            As :meth:`cycle`.
        """
        self._require_booted()
        ex = self._exchanger
        flight = ex.in_flight
        if flight is None:
            return None
        sample = ex.collect(flight)
        ex.check_sample(sample)
        return sample

    def check(self) -> None:
        """Raise a pending fault (EMCY, heartbeat time-out, NMT state, bus) now."""
        self._supervisor.check()

    def drain_events(self) -> list[DriveEvent]:
        """Events since the last call, oldest first."""
        return self._supervisor.drain_events()

    def quick_stop(self) -> None:
        """Quick stop every drive and keep SYNC going until they rest (never raises)."""
        if not self._booted:
            return
        sv, ex = self._supervisor, self._exchanger
        try:
            self._streaming = False
            ex.abandon()  # a pipelined cycle in flight: its answers no longer matter
            ex.controlword = int(Command.QUICK_STOP)
            for d in self._drives:
                if not sv.alive(d):
                    continue
                try:
                    sdo_write(d, ob.CONTROLWORD, 0, ex.controlword)
                except Exception as exc:
                    sv.event(EventLevel.ERROR, d.node_id, None, f"quick stop by SDO failed: {exc}")
            clock = self.clock
            deadline = clock.now() + self.timeouts.quick_stop_s
            next_t = time.monotonic()
            while clock.now() < deadline:
                try:
                    sample = ex.exchange(ex.targets)
                except DriveError as exc:
                    sv.event(EventLevel.ERROR, exc.node, exc.code, f"during quick stop: {exc}")
                    break
                if not any(s in POWERED for s in ex.states(sample)):
                    break
                if not clock.simulated:  # in lockstep each SYNC is one period
                    next_t += self.period_s
                    time.sleep(max(0.0, next_t - time.monotonic()))
            sv.event(EventLevel.WARNING, None, None, "quick stop")
        except Exception as exc:
            sv.event(EventLevel.ERROR, None, None, f"quick stop failed: {exc}")

    def disable(self) -> None:
        """Switch every drive's power stage off ("shutdown", brakes hold); never raises."""
        if not self._booted:
            return
        sv = self._supervisor
        self._streaming = False
        self._exchanger.abandon()
        self._exchanger.controlword = int(Command.SHUTDOWN)
        for d in self._drives:
            if not sv.alive(d):
                continue
            # QUICK STOP ACTIVE ignores "shutdown": only "disable voltage" leaves it (CiA 402).
            cw = (
                int(Command.DISABLE_VOLTAGE)
                if d.state == State.QUICK_STOP_ACTIVE
                else self._exchanger.controlword
            )
            try:
                sdo_write(d, ob.CONTROLWORD, 0, cw)
                self._walker.wait_state(d, lambda s: s not in POWERED, self.timeouts.state_s)
            except Exception as exc:
                sv.event(EventLevel.ERROR, d.node_id, None, f"disable failed: {exc}")
        sv.event(EventLevel.INFO, None, None, "drives disabled")

    def close(self) -> None:
        """Disable the drives if needed, switch their consumer of the master's heartbeat off
        (an orderly end is no fault), stop their PDOs (NMT pre-operational), stop the master's
        heartbeat and detach from the network (which the caller disconnects); never raises."""
        if self._closed:
            return
        sv = self._supervisor
        try:
            if self._booted and (self._streaming or any(d.state in POWERED for d in self._drives)):
                self.disable()
            sv.monitoring = False
            if self._booted and self.network.bus is not None:
                for d in self._drives:
                    if not sv.alive(d):
                        continue
                    try:
                        sdo_write(d, ob.CONSUMER_HEARTBEAT, 1, 0)
                    except Exception as exc:
                        sv.event(EventLevel.ERROR, d.node_id, None, f"consumer off failed: {exc}")
                for d in self._drives:
                    try:
                        send(self.network, 0x000, bytes([_NMT_PRE_OPERATIONAL, d.node_id]))
                    except Exception as exc:
                        sv.event(
                            EventLevel.ERROR, d.node_id, None, f"NMT pre-operational failed: {exc}"
                        )
        finally:
            self._producer.stop()
            if isinstance(self.clock, LockstepClock):
                self.clock.detach("master")
            self._closed = True
            self._booted = False
            notifier = self.network.notifier
            if notifier is not None and self._listener in notifier.listeners:
                notifier.remove_listener(self._listener)
            for d in self._drives:
                if self.network.nodes.get(d.node_id) is d.node:
                    try:
                        del self.network[d.node_id]
                    except Exception as exc:
                        logger.warning("drive master: removing node %d: %s", d.node_id, exc)

    def __enter__(self) -> Master:
        return self

    def _drop_in_flight(self, why: str) -> None:
        """Give up the pipelined cycle in flight, with a warning event."""
        flight = self._exchanger.in_flight
        self._exchanger.abandon()
        if flight is not None:
            self._supervisor.event(
                EventLevel.WARNING,
                None,
                None,
                f"TPDOs of cycle {flight.cycle} not collected before {why}: dropped",
            )

    def _require_booted(self) -> None:
        if self._closed:
            raise DriveError("the master is closed")
        if not self._booted:
            raise DriveError("the drives are not booted (call boot() first)")
