"""CiA 402 drive state machine: statusword decoding and controlword commands.

Shared by the master (which walks a drive to Operation enabled) and the simulated drive (which
implements the transitions), so both read the same bit patterns from one place.
"""

from __future__ import annotations

import enum


class State(enum.Enum):
    NOT_READY_TO_SWITCH_ON = "Not ready to switch on"
    SWITCH_ON_DISABLED = "Switch on disabled"
    READY_TO_SWITCH_ON = "Ready to switch on"
    SWITCHED_ON = "Switched on"
    OPERATION_ENABLED = "Operation enabled"
    QUICK_STOP_ACTIVE = "Quick stop active"
    FAULT_REACTION_ACTIVE = "Fault reaction active"
    FAULT = "Fault"
    UNKNOWN = "Unknown"

    def __str__(self) -> str:
        return self.value


# (mask, value, state): statusword bits 0-3, 5 and 6 as CiA 402 defines them.
_DECODE: tuple[tuple[int, int, State], ...] = (
    (0x4F, 0x00, State.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State.SWITCHED_ON),
    (0x6F, 0x27, State.OPERATION_ENABLED),
    (0x6F, 0x07, State.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State.FAULT),
)

_ENCODE: dict[State, int] = {
    State.NOT_READY_TO_SWITCH_ON: 0x00,
    State.SWITCH_ON_DISABLED: 0x40,
    State.READY_TO_SWITCH_ON: 0x21,
    State.SWITCHED_ON: 0x23,
    State.OPERATION_ENABLED: 0x27,
    State.QUICK_STOP_ACTIVE: 0x07,
    State.FAULT_REACTION_ACTIVE: 0x0F,
    State.FAULT: 0x08,
}

# Statusword bits beyond the state
SW_VOLTAGE_ENABLED = 1 << 4
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
SW_BIT12 = 1 << 12  # CSP: drive follows the target; homing: homing attained
SW_BIT13 = 1 << 13  # CSP: following error; homing: homing error

# Controlword commands (bit 8, halt, is never set: a set halt bit blocks mode changes on many drives)
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_DISABLE_OPERATION = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_FAULT_RESET = 0x0080
CW_HOMING_START = 0x0010  # bit 4 in homing mode (6)

MODE_HOMING = 6
MODE_CSP = 8


def decode(statusword: int) -> State:
    for mask, value, state in _DECODE:
        if statusword & mask == value:
            return state
    return State.UNKNOWN


def statusword_for(state: State, extra: int = 0) -> int:
    """The statusword a drive in ``state`` reports (voltage-enabled and remote bits as drives set)."""
    sw = _ENCODE[state] | SW_REMOTE
    if state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED,
                 State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE):
        sw |= SW_VOLTAGE_ENABLED
    return sw | extra


class Command(enum.Enum):
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"
    ENABLE_OPERATION = "enable operation"
    FAULT_RESET = "fault reset"


def command_of(controlword: int, previous: int = 0) -> Command:
    """Which command a controlword carries (fault reset needs bit 7 rising from ``previous``)."""
    if controlword & 0x80 and not previous & 0x80:
        return Command.FAULT_RESET
    if controlword & 0x02 == 0:
        return Command.DISABLE_VOLTAGE
    if controlword & 0x06 == 0x02:
        return Command.QUICK_STOP
    if controlword & 0x07 == 0x06:
        return Command.SHUTDOWN
    if controlword & 0x0F == 0x07:
        return Command.SWITCH_ON
    return Command.ENABLE_OPERATION


def next_step(state: State) -> tuple[int, State] | None:
    """The controlword that moves a drive one step toward Operation enabled, and the state expected.

    ``None`` when the drive is already there, or is in a state that needs a fault reset first.
    """
    return {
        State.SWITCH_ON_DISABLED: (CW_SHUTDOWN, State.READY_TO_SWITCH_ON),
        State.READY_TO_SWITCH_ON: (CW_SWITCH_ON, State.SWITCHED_ON),
        State.SWITCHED_ON: (CW_ENABLE_OPERATION, State.OPERATION_ENABLED),
        State.QUICK_STOP_ACTIVE: (CW_ENABLE_OPERATION, State.OPERATION_ENABLED),
    }.get(state)
