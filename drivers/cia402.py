"""The CiA 402 drive state machine: states, statusword decoding, controlword commands.

Both sides use this module: the master decodes statuswords and picks the controlword that moves a
drive towards a goal state; the simulated drive applies controlwords (the transitions of CiA 402
figure "state machine") and encodes its statusword.
"""

from __future__ import annotations

from enum import IntEnum, StrEnum

from drivegain.errors import DriveError


class State(StrEnum):
    """CiA 402 power drive system states.

    A :class:`~enum.StrEnum` whose values are the names: it is what :class:`DriveError` carries
    as ``state``, and prints and compares as the plain name (``"FAULT"``).
    """

    NOT_READY_TO_SWITCH_ON = "NOT_READY_TO_SWITCH_ON"
    SWITCH_ON_DISABLED = "SWITCH_ON_DISABLED"
    READY_TO_SWITCH_ON = "READY_TO_SWITCH_ON"
    SWITCHED_ON = "SWITCHED_ON"
    OPERATION_ENABLED = "OPERATION_ENABLED"
    QUICK_STOP_ACTIVE = "QUICK_STOP_ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT_REACTION_ACTIVE"
    FAULT = "FAULT"


# (mask, value) of the statusword bits 0-3, 5, 6 that identify each state.
_STATUS_PATTERNS: tuple[tuple[int, int, State], ...] = (
    (0x4F, 0x00, State.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State.SWITCHED_ON),
    (0x6F, 0x27, State.OPERATION_ENABLED),
    (0x6F, 0x07, State.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State.FAULT),
)

#: Statusword bits outside the state pattern.
SW_VOLTAGE_ENABLED = 1 << 4
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_FOLLOWING = 1 << 12  # CSP: "drive follows the command value"
SW_FOLLOWING_ERROR = 1 << 13


def decode_statusword(sw: int, node: int | None = None) -> State:
    """The CiA 402 state shown by a statusword (0x6041) of node ``node`` (for the error).

    Raises
    ------
    DriveError
        The bits match no state (a corrupt frame or a drive outside the profile); the
        statusword is the code.
    """
    for mask, value, state in _STATUS_PATTERNS:
        if sw & mask == value:
            return state
    raise DriveError(f"statusword 0x{sw:04X} shows no CiA 402 state", node=node, code=sw)


def encode_statusword(state: State, extra: int = 0) -> int:
    """A statusword showing ``state`` (bit 5 quick stop and bit 4 voltage set as a drive would)
    with the further bits ``extra`` (remote, following, ...)."""
    base = {
        State.NOT_READY_TO_SWITCH_ON: 0x00,
        State.SWITCH_ON_DISABLED: 0x40,
        State.READY_TO_SWITCH_ON: 0x21 | SW_VOLTAGE_ENABLED,
        State.SWITCHED_ON: 0x23 | SW_VOLTAGE_ENABLED,
        State.OPERATION_ENABLED: 0x27 | SW_VOLTAGE_ENABLED,
        State.QUICK_STOP_ACTIVE: 0x07 | SW_VOLTAGE_ENABLED,
        State.FAULT_REACTION_ACTIVE: 0x0F,
        State.FAULT: 0x08,
    }[state]
    return base | extra


class Command(IntEnum):
    """Controlword (0x6040) values of the device control commands."""

    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    DISABLE_OPERATION = 0x0007
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080


CW_FAULT_RESET_BIT = 0x0080

#: States in which the power stage is on and the motor is controlled.
POWERED = frozenset({State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE})
#: States the drive leaves by itself (no command needed).
TRANSIENT = frozenset({State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE})


def command_towards(state: State, goal: State) -> int | None:
    """The controlword that moves a drive one transition from ``state`` towards ``goal``.

    ``goal`` is one of SWITCH_ON_DISABLED, READY_TO_SWITCH_ON, SWITCHED_ON, OPERATION_ENABLED.
    Returns ``None`` when ``state`` is ``goal`` or a transient state (wait for the drive).
    FAULT is left with a fault reset (the caller produces the rising edge of bit 7).
    """
    if state == goal or state in TRANSIENT:
        return None
    if state == State.FAULT:
        return int(Command.FAULT_RESET)
    if state == State.QUICK_STOP_ACTIVE:
        return int(Command.DISABLE_VOLTAGE)
    if goal == State.SWITCH_ON_DISABLED:
        return int(Command.DISABLE_VOLTAGE)
    order = (
        State.SWITCH_ON_DISABLED,
        State.READY_TO_SWITCH_ON,
        State.SWITCHED_ON,
        State.OPERATION_ENABLED,
    )
    here, there = order.index(state), order.index(goal)
    if there > here:
        step = order[here + 1]
        return {
            State.READY_TO_SWITCH_ON: int(Command.SHUTDOWN),
            State.SWITCHED_ON: int(Command.SWITCH_ON),
            State.OPERATION_ENABLED: int(Command.ENABLE_OPERATION),
        }[step]
    # Going down: OPERATION_ENABLED -> SWITCHED_ON (disable operation) -> READY (shutdown).
    if goal == State.SWITCHED_ON:
        return int(Command.DISABLE_OPERATION)
    return int(Command.SHUTDOWN)


#: Controlword commands of CiA 402 as (mask, value): given when ``cw & mask == value``.
_SHUTDOWN = (0x87, 0x06)
_SWITCH_ON = (0x8F, 0x07)  # also "disable operation" from OPERATION_ENABLED
_ENABLE = (0x8F, 0x0F)
_DISABLE_VOLTAGE = (0x82, 0x00)
_QUICK_STOP = (0x86, 0x02)

#: Command-driven transitions, in the order they are tested (the masks overlap, so the order
#: decides which command a controlword is read as).
_TRANSITIONS: dict[State, tuple[tuple[tuple[int, int], State], ...]] = {
    State.SWITCH_ON_DISABLED: ((_SHUTDOWN, State.READY_TO_SWITCH_ON),),
    State.READY_TO_SWITCH_ON: (
        (_SWITCH_ON, State.SWITCHED_ON),
        (_ENABLE, State.OPERATION_ENABLED),
        (_DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED),
        (_QUICK_STOP, State.SWITCH_ON_DISABLED),
    ),
    State.SWITCHED_ON: (
        (_ENABLE, State.OPERATION_ENABLED),
        (_SHUTDOWN, State.READY_TO_SWITCH_ON),
        (_DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED),
        (_QUICK_STOP, State.SWITCH_ON_DISABLED),
    ),
    State.OPERATION_ENABLED: (
        (_SWITCH_ON, State.SWITCHED_ON),
        (_SHUTDOWN, State.READY_TO_SWITCH_ON),
        (_DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED),
        (_QUICK_STOP, State.QUICK_STOP_ACTIVE),
    ),
    State.QUICK_STOP_ACTIVE: ((_DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED),),
}


def apply_controlword(state: State, cw: int, previous_cw: int) -> State:
    """Drive side: the state after receiving controlword ``cw`` in ``state``.

    Implements the command-driven transitions 2-12 and 15 of CiA 402 (transitions 3 and 4
    combined for "switch on + enable operation" from READY_TO_SWITCH_ON, as most drives do; no
    transition 16: quick stop option codes 1-4, the drive ends a quick stop switched off).
    Transitions a drive makes by itself (0, 1, 13, 14, the end of a quick stop) are the caller's.
    ``previous_cw`` detects the rising edge of the fault reset bit.
    """
    if state == State.FAULT:
        rising = bool(cw & CW_FAULT_RESET_BIT) and not previous_cw & CW_FAULT_RESET_BIT
        return State.SWITCH_ON_DISABLED if rising else state
    for (mask, value), after in _TRANSITIONS.get(state, ()):
        if cw & mask == value:
            return after
    return state
