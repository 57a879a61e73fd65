"""The CiA 402 state machine: statusword decoding, the drive's transitions, the master's path."""

from __future__ import annotations

import pytest

from drivegain.drivers.cia402 import (
    Command,
    State,
    apply_controlword,
    command_towards,
    decode_statusword,
    encode_statusword,
)
from drivegain.errors import DriveError

S = State

# CiA 402 table "statusword bits for the states" (x = don't care), with typical drive values.
DECODE = [
    (0x0000, S.NOT_READY_TO_SWITCH_ON),
    (0x0250, S.SWITCH_ON_DISABLED),
    (0x0040, S.SWITCH_ON_DISABLED),
    (0x0221, S.READY_TO_SWITCH_ON),
    (0x0231, S.READY_TO_SWITCH_ON),
    (0x0233, S.SWITCHED_ON),
    (0x0237, S.OPERATION_ENABLED),
    (0x1637, S.OPERATION_ENABLED),
    (0x0217, S.QUICK_STOP_ACTIVE),
    (0x021F, S.FAULT_REACTION_ACTIVE),
    (0x0208, S.FAULT),
    (0x0218, S.FAULT),
]


@pytest.mark.parametrize(("sw", "state"), DECODE)
def test_decode_statusword(sw, state):
    assert decode_statusword(sw) == state


@pytest.mark.parametrize("sw", [0x0001, 0x0003, 0x0027 & ~0x20 | 0x40, 0x0061])
def test_invalid_statusword(sw):
    with pytest.raises(DriveError) as err:
        decode_statusword(sw, node=4)
    assert (err.value.node, err.value.code) == (4, sw)


def test_a_drive_error_carries_the_state_and_prints_its_name():
    err = DriveError("drive in fault", node=3, state=S.FAULT, code=0x2310)
    assert err.state is S.FAULT and err.state == "FAULT"
    assert str(err) == "drive in fault (node 3, state FAULT, code 0x2310)"


@pytest.mark.parametrize("state", list(State))
def test_encode_decode_round_trip(state):
    assert decode_statusword(encode_statusword(state, 0x1200)) == state


# CiA 402 transitions driven by the controlword: (from, controlword, to).
TRANSITIONS = [
    (S.SWITCH_ON_DISABLED, 0x06, S.READY_TO_SWITCH_ON),  # 2
    (S.READY_TO_SWITCH_ON, 0x07, S.SWITCHED_ON),  # 3
    (S.SWITCHED_ON, 0x0F, S.OPERATION_ENABLED),  # 4
    (S.OPERATION_ENABLED, 0x07, S.SWITCHED_ON),  # 5
    (S.SWITCHED_ON, 0x06, S.READY_TO_SWITCH_ON),  # 6
    (S.READY_TO_SWITCH_ON, 0x00, S.SWITCH_ON_DISABLED),  # 7, disable voltage
    (S.READY_TO_SWITCH_ON, 0x02, S.SWITCH_ON_DISABLED),  # 7, quick stop
    (S.OPERATION_ENABLED, 0x06, S.READY_TO_SWITCH_ON),  # 8
    (S.OPERATION_ENABLED, 0x00, S.SWITCH_ON_DISABLED),  # 9
    (S.SWITCHED_ON, 0x00, S.SWITCH_ON_DISABLED),  # 10
    (S.OPERATION_ENABLED, 0x02, S.QUICK_STOP_ACTIVE),  # 11
    (S.QUICK_STOP_ACTIVE, 0x00, S.SWITCH_ON_DISABLED),  # 12
    (S.READY_TO_SWITCH_ON, 0x0F, S.OPERATION_ENABLED),  # 3 + 4
    # No transition:
    (S.SWITCH_ON_DISABLED, 0x0F, S.SWITCH_ON_DISABLED),
    (S.SWITCH_ON_DISABLED, 0x07, S.SWITCH_ON_DISABLED),
    (S.QUICK_STOP_ACTIVE, 0x0F, S.QUICK_STOP_ACTIVE),  # no transition 16 with option code 2
    (S.FAULT, 0x0F, S.FAULT),
    (S.OPERATION_ENABLED, 0x8F, S.OPERATION_ENABLED),  # bit 7 outside FAULT: not a command
]


@pytest.mark.parametrize(("start", "cw", "end"), TRANSITIONS)
def test_drive_transitions(start, cw, end):
    assert apply_controlword(start, cw, previous_cw=0) == end


def test_fault_reset_needs_a_rising_edge():
    assert apply_controlword(S.FAULT, 0x80, previous_cw=0x00) == S.SWITCH_ON_DISABLED  # 15
    assert apply_controlword(S.FAULT, 0x80, previous_cw=0x80) == S.FAULT
    assert apply_controlword(S.FAULT, 0x8F, previous_cw=0x0F) == S.SWITCH_ON_DISABLED


@pytest.mark.parametrize(
    "start", [s for s in State if s not in (S.NOT_READY_TO_SWITCH_ON, S.FAULT_REACTION_ACTIVE)]
)
@pytest.mark.parametrize(
    "goal",
    [S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED],
)
def test_master_commands_reach_every_goal(start, goal):
    state, previous = start, 0
    for _ in range(6):
        cmd = command_towards(state, goal)
        if cmd is None:
            break
        if state == S.FAULT:  # the master clears bit 7 first
            previous = 0
        state = apply_controlword(state, cmd, previous)
        previous = cmd
    assert state == goal


def test_command_values():
    assert (Command.SHUTDOWN, Command.SWITCH_ON, Command.ENABLE_OPERATION) == (0x06, 0x07, 0x0F)
    assert (Command.DISABLE_VOLTAGE, Command.QUICK_STOP, Command.FAULT_RESET) == (0, 0x02, 0x80)
