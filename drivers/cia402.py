"""The CiA 402 drive state machine (IEC 61800-7-201), written once for the driver and the emulated drive.

States and their statusword bits, the controlword commands, the modes of operation this project uses, and
the device-control transitions: :func:`state_of` reads a statusword (the driver), :func:`next_state` applies a
controlword to a state (the emulated drive, ``sim_backend.can_drive_emulator``).
"""

from __future__ import annotations

NOT_READY = "not ready to switch on"
SWITCH_ON_DISABLED = "switch on disabled"
READY_TO_SWITCH_ON = "ready to switch on"
SWITCHED_ON = "switched on"
OPERATION_ENABLED = "operation enabled"
QUICK_STOP_ACTIVE = "quick stop active"
FAULT_REACTION_ACTIVE = "fault reaction active"
FAULT = "fault"

# statusword bits 0-3, 5 and 6 of each state (the bits state_of reads)
STATUSWORD_BITS = {
    NOT_READY: 0x0000,
    SWITCH_ON_DISABLED: 0x0040,
    READY_TO_SWITCH_ON: 0x0031,
    SWITCHED_ON: 0x0033,
    OPERATION_ENABLED: 0x0037,
    QUICK_STOP_ACTIVE: 0x0017,
    FAULT_REACTION_ACTIVE: 0x000F,
    FAULT: 0x0008,
}
SW_FAULT = 0x0008
SW_REMOTE = 0x0200
SW_FOLLOWS_COMMAND = 0x1000  # cyclic synchronous modes: the drive follows the target

CW_DISABLE_VOLTAGE = 0x00
CW_QUICK_STOP = 0x02
CW_SHUTDOWN = 0x06
CW_SWITCH_ON = 0x07
CW_ENABLE = 0x0F
CW_FAULT_RESET = 0x80

MODE_CSV = 9
MODE_CST = 10
MODE_NAMES = {MODE_CSV: "cyclic synchronous velocity", MODE_CST: "cyclic synchronous torque"}


def state_of(statusword: int) -> str:
    """Name of the CiA 402 state a statusword encodes."""
    low = statusword & 0x4F
    if low == 0x00:
        return NOT_READY
    if low == 0x40:
        return SWITCH_ON_DISABLED
    sw = statusword & 0x6F
    if sw == 0x21:
        return READY_TO_SWITCH_ON
    if sw == 0x23:
        return SWITCHED_ON
    if sw == 0x27:
        return OPERATION_ENABLED
    if sw == 0x07:
        return QUICK_STOP_ACTIVE
    if low == 0x0F:
        return FAULT_REACTION_ACTIVE
    if low == 0x08:
        return FAULT
    return f"unknown (statusword 0x{statusword:04X})"


def next_state(state: str, controlword: int, reset_edge: bool = False, quick_stop_option: int = 2) -> str:
    """The state a drive in ``state`` enters on ``controlword`` (CiA 402 transitions 2-12, 15 and 16); ``state``
    itself when none applies.

    ``reset_edge``: bit 7 rose with this controlword (fault reset, transition 15, the only way out of fault).
    ``quick_stop_option`` (0x605A): 0 ends a quick stop in switch on disabled at once; 5-8 let quick stop active
    return to operation enabled on enable operation (transition 16).
    """
    if state == FAULT:
        return SWITCH_ON_DISABLED if reset_edge else FAULT
    if state in (FAULT_REACTION_ACTIVE, NOT_READY) or controlword & CW_FAULT_RESET:
        return state
    disable_voltage = (controlword & 0x02) == 0
    quick_stop = (controlword & 0x06) == 0x02
    shutdown = (controlword & 0x07) == 0x06
    switch_on = (controlword & 0x0F) == 0x07
    enable = (controlword & 0x0F) == 0x0F
    if state == SWITCH_ON_DISABLED:
        return READY_TO_SWITCH_ON if shutdown else state
    if state == READY_TO_SWITCH_ON:
        if disable_voltage or quick_stop:
            return SWITCH_ON_DISABLED
        return SWITCHED_ON if switch_on else OPERATION_ENABLED if enable else state
    if state == SWITCHED_ON:
        if disable_voltage or quick_stop:
            return SWITCH_ON_DISABLED
        return READY_TO_SWITCH_ON if shutdown else OPERATION_ENABLED if enable else state
    if state == OPERATION_ENABLED:
        if disable_voltage:
            return SWITCH_ON_DISABLED
        if quick_stop:
            return SWITCH_ON_DISABLED if quick_stop_option == 0 else QUICK_STOP_ACTIVE
        return READY_TO_SWITCH_ON if shutdown else SWITCHED_ON if switch_on else state
    if state == QUICK_STOP_ACTIVE:
        if disable_voltage:
            return SWITCH_ON_DISABLED
        return OPERATION_ENABLED if enable and quick_stop_option in (5, 6, 7, 8) else state
    return state
