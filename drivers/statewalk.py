"""The CiA 402 state walk of one drive by SDO: read the statusword, send the controlword that moves
it one transition towards a goal, wait for the transition, each within its time limit.

The transitions themselves are :mod:`.cia402` (shared with the simulated drives); this module is
the master's side, with the time-outs and the error reports (node, state, 0x603F error code).
"""

from __future__ import annotations

from collections.abc import Callable

from drivegain.drivers import objects as ob
from drivegain.drivers.cia402 import Command, State, command_towards, decode_statusword
from drivegain.drivers.link import DriveLink, Timeouts, error_code, sdo_read, sdo_write
from drivegain.drivers.supervisor import Supervisor
from drivegain.errors import DriveError

#: Most transitions any walk needs (FAULT -> ... -> OPERATION_ENABLED is 4, plus transients).
_MAX_STEPS = 12


def _other_than(state: State) -> Callable[[State], bool]:
    """Accept any state but ``state`` (the end of a transition out of it)."""
    return lambda s: s != state


class StateWalker:
    """Moves drives through the CiA 402 state machine by SDO.

    Parameters
    ----------
    supervisor
        Records every state seen (:meth:`Supervisor.note_state`).
    timeouts
        ``state_s`` per transition, ``poll_s`` between statusword reads.
    """

    def __init__(self, supervisor: Supervisor, timeouts: Timeouts):
        self.supervisor = supervisor
        self.timeouts = timeouts

    def read_state(self, d: DriveLink) -> State:
        """The drive's state from its statusword (0x6041), read by SDO.

        Raises
        ------
        DriveError
            No answer, or a statusword that shows no CiA 402 state (code = statusword).
        """
        state = decode_statusword(sdo_read(d, ob.STATUSWORD), node=d.node_id)
        self.supervisor.note_state(d, state)
        return state

    def wait_state(self, d: DriveLink, accept: Callable[[State], bool], timeout: float) -> State:
        """Poll the statusword until ``accept(state)`` or ``timeout`` s; return the last state
        read."""
        clock = self.supervisor.clock
        deadline = clock.now() + timeout
        while True:
            state = self.read_state(d)
            if accept(state) or clock.now() >= deadline:
                return state
            clock.sleep(self.timeouts.poll_s, f"node {d.node_id} to leave {state.name}")

    def walk(self, d: DriveLink, goal: State, state: State | None = None) -> None:
        """Move a drive to ``goal`` one transition at a time, each within ``state_s``.

        ``state`` is the drive's current state if just read. FAULT is left by one fault reset
        (rising edge of controlword bit 7); a drive that faults again is not reset twice.

        Raises
        ------
        DriveError
            A transition did not happen in time, or ``goal`` cannot be reached; node, state
            and the drive's error code 0x603F are set.
        """
        state = state if state is not None else self.read_state(d)
        resets = 0
        for _ in range(_MAX_STEPS):
            if state == goal:
                return
            cmd = command_towards(state, goal)
            before = state
            if cmd is None:  # transient state: the drive leaves it by itself
                state = self.wait_state(d, _other_than(before), self.timeouts.state_s)
            else:
                if before == State.FAULT:
                    if resets:
                        break
                    resets += 1
                    # Fault reset acts on the rising edge of bit 7: clear it first.
                    sdo_write(d, ob.CONTROLWORD, 0, int(Command.DISABLE_VOLTAGE))
                sdo_write(d, ob.CONTROLWORD, 0, cmd)
                state = self.wait_state(d, _other_than(before), self.timeouts.state_s)
            if state == before:
                raise DriveError(
                    f"no transition out of {before.name} towards {goal.name} "
                    f"within {self.timeouts.state_s} s",
                    node=d.node_id,
                    state=before,
                    code=error_code(d),
                )
        raise DriveError(
            f"cannot reach {goal.name} (stuck in {state.name})",
            node=d.node_id,
            state=state,
            code=error_code(d),
        )
