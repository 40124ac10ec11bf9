"""The CiA 402 power state machine: the statusword a drive shows, the controlword a master sends.

Both sides are here, because both run in this project: the master side steps every drive towards
the state the runtime wants, one transition per tick (:class:`PowerStepper`); the device side
(:func:`device_next_state`) is what the simulated drives do with a controlword.

::

    NOT READY TO SWITCH ON --(auto)--> SWITCH ON DISABLED --shutdown 0x06--> READY TO SWITCH ON
      --switch on 0x07--> SWITCHED ON --enable operation 0x0F--> OPERATION ENABLED
    disable voltage 0x00 from any of the last three: back to SWITCH ON DISABLED (no torque)
    quick stop 0x02 from OPERATION ENABLED: QUICK STOP ACTIVE, then SWITCH ON DISABLED once the
      quick stop is over (0x605A: at once, or at the end of the torque ramp) or on disable voltage
    a fault anywhere: FAULT REACTION ACTIVE, then FAULT; a rising edge of bit 7 (0x80): SWITCH ON DISABLED

Statusword bits 14 and 15 are manufacturer-specific in CiA 402; the DAROR drives report the
operator's and the pilot's e-stop inputs there (hal/canopen/daror_sea.eds). Where a drive of
another make reports them is its robot file's ``estop`` (an object and two bits,
:mod:`hal.canopen.profile`): on other drives bits 14 and 15 mean other things.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from hal.interface import DriveState

__all__ = [
    "CW_DISABLE_VOLTAGE",
    "CW_ENABLE_OPERATION",
    "CW_FAULT_RESET",
    "CW_QUICK_STOP",
    "CW_SHUTDOWN",
    "CW_SWITCH_ON",
    "SW_ESTOP_OPERATOR",
    "SW_ESTOP_PILOT",
    "PowerState",
    "PowerStepper",
    "StepOutcome",
    "decode_statusword",
    "device_next_state",
    "drive_state",
    "statusword_of",
]

#: Controlword commands (object 0x6040).
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_FAULT_RESET = 0x0080  # acts on its rising edge

#: Statusword (0x6041) manufacturer bits of the DAROR drives: the e-stop inputs (their profile's ``estop``).
SW_ESTOP_OPERATOR = 1 << 14
SW_ESTOP_PILOT = 1 << 15
#: Statusword bit 4: the power stage has voltage.
SW_VOLTAGE_ENABLED = 1 << 4
#: Statusword bit 9: the drive follows the controlword and the PDOs (remote).
SW_REMOTE = 1 << 9


class PowerState(Enum):
    """The eight states of the CiA 402 power state machine."""

    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"


# (mask, value) of each state in the statusword, CiA 402 table 30.
_PATTERNS: tuple[tuple[int, int, PowerState], ...] = (
    (0x004F, 0x0000, PowerState.NOT_READY_TO_SWITCH_ON),
    (0x004F, 0x0040, PowerState.SWITCH_ON_DISABLED),
    (0x006F, 0x0021, PowerState.READY_TO_SWITCH_ON),
    (0x006F, 0x0023, PowerState.SWITCHED_ON),
    (0x006F, 0x0027, PowerState.OPERATION_ENABLED),
    (0x006F, 0x0007, PowerState.QUICK_STOP_ACTIVE),
    (0x004F, 0x000F, PowerState.FAULT_REACTION_ACTIVE),
    (0x004F, 0x0008, PowerState.FAULT),
)
_BITS = {state: value for _, value, state in _PATTERNS}


def decode_statusword(statusword: int) -> PowerState | None:
    """The power state a statusword shows (None: a pattern CiA 402 does not define)."""
    for mask, value, state in _PATTERNS:
        if statusword & mask == value:
            return state
    return None


def statusword_of(state: PowerState, estop_operator: bool = False, estop_pilot: bool = False) -> int:
    """The statusword a DAROR drive shows in ``state`` (remote, voltage bit as the state has it, e-stop bits)."""
    word = _BITS[state] | SW_REMOTE
    if state in (PowerState.READY_TO_SWITCH_ON, PowerState.SWITCHED_ON, PowerState.OPERATION_ENABLED):
        word |= SW_VOLTAGE_ENABLED | 0x0020  # quick stop bit 5 is active low: 1 = no quick stop
    elif state is PowerState.QUICK_STOP_ACTIVE:
        word |= SW_VOLTAGE_ENABLED  # the power stage still has voltage while it stops
    if estop_operator:
        word |= SW_ESTOP_OPERATOR
    if estop_pilot:
        word |= SW_ESTOP_PILOT
    return word


def drive_state(state: PowerState | None) -> DriveState:
    """The HAL's view of a power state: only OPERATION ENABLED applies torque; the fault states are FAULT."""
    if state is PowerState.OPERATION_ENABLED:
        return DriveState.ENABLED
    if state in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
        return DriveState.FAULT
    return DriveState.DISABLED


def device_next_state(state: PowerState, controlword: int, previous_controlword: int) -> PowerState:
    """What a drive in ``state`` does with ``controlword`` (the device side; CiA 402 transitions 2-16).

    The fault states are left only by a rising edge of bit 7 (transition 15); FAULT REACTION
    ACTIVE ends in FAULT by itself (the caller steps it); NOT READY TO SWITCH ON ends by itself.
    QUICK STOP ACTIVE is left for SWITCH ON DISABLED by disable voltage (transition 12); otherwise
    it lasts until the quick stop is over, which the caller judges (0x605A: at once, or when the
    torque ramp reached zero). The DAROR drives take quick stop option codes 0 and 1 only, which go
    on to SWITCH ON DISABLED: transition 16 back to OPERATION ENABLED (codes 5-8) does not exist here.
    """
    if state is PowerState.FAULT:
        if controlword & CW_FAULT_RESET and not previous_controlword & CW_FAULT_RESET:
            return PowerState.SWITCH_ON_DISABLED
        return state
    if state in (PowerState.FAULT_REACTION_ACTIVE, PowerState.NOT_READY_TO_SWITCH_ON):
        return state
    if controlword & CW_FAULT_RESET:
        return state  # a fault reset outside FAULT does nothing (CiA 402: bit 7 takes precedence)
    enable_voltage = bool(controlword & 0x0002)
    quick_stop_off = bool(controlword & 0x0004)  # active low: set means no quick stop
    switch_on = bool(controlword & 0x0001)
    enable_operation = bool(controlword & 0x0008)
    if not enable_voltage:
        return PowerState.SWITCH_ON_DISABLED  # transitions 7, 9, 10, 12
    if state is PowerState.QUICK_STOP_ACTIVE:
        return state  # the quick stop goes on; the caller ends it (transition 12)
    if not quick_stop_off:  # quick stop: 11 from operation enabled, else 7 / 10
        return PowerState.QUICK_STOP_ACTIVE if state is PowerState.OPERATION_ENABLED else PowerState.SWITCH_ON_DISABLED
    if state is PowerState.SWITCH_ON_DISABLED:
        return PowerState.READY_TO_SWITCH_ON if not switch_on else state  # 2: shutdown (0x06) only
    if state is PowerState.READY_TO_SWITCH_ON:
        if switch_on and enable_operation:
            return PowerState.OPERATION_ENABLED  # 3 + 4 at once (0x0F), as most drives allow
        return PowerState.SWITCHED_ON if switch_on else state  # 3
    if state is PowerState.SWITCHED_ON:
        if not switch_on:
            return PowerState.READY_TO_SWITCH_ON  # 6
        return PowerState.OPERATION_ENABLED if enable_operation else state  # 4
    # OPERATION ENABLED
    if not switch_on:
        return PowerState.READY_TO_SWITCH_ON  # 8
    return state if enable_operation else PowerState.SWITCHED_ON  # 5


def _towards_torque(state: PowerState) -> int:
    """The controlword that moves a drive in ``state`` (not a fault state) one step towards OPERATION ENABLED.

    Tests by identity, not a dict of states: an Enum's hash is a Python call, and this runs per drive and tick.
    """
    if state is PowerState.OPERATION_ENABLED or state is PowerState.SWITCHED_ON:
        return CW_ENABLE_OPERATION
    if state is PowerState.SWITCH_ON_DISABLED:
        return CW_SHUTDOWN
    if state is PowerState.READY_TO_SWITCH_ON:
        return CW_SWITCH_ON
    if state is PowerState.NOT_READY_TO_SWITCH_ON or state is PowerState.QUICK_STOP_ACTIVE:
        return CW_DISABLE_VOLTAGE
    raise KeyError(state)  # the fault states are handled before: a bug


@dataclass(frozen=True, slots=True)
class StepOutcome:
    """What the master sends a drive this tick, and a fault to report (a drive that did not follow)."""

    controlword: int
    timed_out: str | None = None


#: The outcome of each controlword with nothing to report: nearly every step's, made once (frozen, shared).
_QUIET_OUTCOMES: dict[int, StepOutcome] = {}
#: A session's step with torque wanted from a drive in OPERATION ENABLED (PowerStepper.step's first test)
_QUIET_ENABLE_OPERATION = _QUIET_OUTCOMES[CW_ENABLE_OPERATION] = StepOutcome(CW_ENABLE_OPERATION)


class PowerStepper:
    """The master's side for one drive: one controlword per tick towards the wanted state.

    Wanting torque: SWITCH ON DISABLED -> shutdown -> READY -> switch on -> SWITCHED ON -> enable
    operation -> OPERATION ENABLED; a drive in FAULT stays there (torque is never re-enabled by
    itself) until :meth:`request_fault_reset`, which sends one rising edge of bit 7 (a tick of 0x00,
    then a tick of 0x80). Not wanting torque: disable voltage (0x00) at once, whatever the state.

    Timeouts are counted in ticks, not read from a clock, so a lock-step run is deterministic: a
    drive that does not show the state a command asks for within ``timeout_ticks`` is reported
    once (:attr:`StepOutcome.timed_out`) and the stepper starts over from what the drive shows.

    Args:
        timeout_ticks: ticks a transition may take (at least 2: the command goes out at one SYNC,
            the drive's statusword comes back with the next).
    """

    def __init__(self, timeout_ticks: int) -> None:
        self.timeout_ticks = max(int(timeout_ticks), 2)
        self._command = CW_DISABLE_VOLTAGE
        self._waited = 0
        self._reset_phase = 0  # 0 none, 1 sent 0x00, 2 sent 0x80

    def request_fault_reset(self) -> None:
        """Send one fault-reset edge at the next ticks (the drive leaves FAULT if its cause is gone).

        A drive still in FAULT REACTION ACTIVE (ramping its torque down) gets the edge once it is in FAULT.
        A drive that faults again after it showed FAULT, before the edge went out, keeps the new fault:
        the request is dropped (a reset acknowledges the faults before it, never one after).
        """
        self._reset_phase = 1

    def step(self, state: PowerState | None, want_torque: bool, fresh: bool = True) -> StepOutcome:
        """The controlword for this tick, from the state the drive showed last and what the runtime wants.

        ``fresh``: the drive reported ``state`` since the last step. A tick without a report (the
        master wrote twice without reading, or the drive's TPDO is late) is no tick the drive
        "stayed" in it: the wait is not counted (a late drive is the watchdogs' to judge).
        """
        # Nearly every tick of a session, answered first: what the general steps below give for it
        if (
            state is PowerState.OPERATION_ENABLED
            and want_torque
            and self._command == CW_ENABLE_OPERATION
            and not self._reset_phase
        ):
            return _QUIET_ENABLE_OPERATION
        if self._reset_phase == 2 and state is PowerState.FAULT_REACTION_ACTIVE:
            # It showed FAULT (the 0x00 went out), now a fault reaction again: a new fault since the
            # request. The reset was asked for the fault before; this one holds until a reset of its own.
            self._reset_phase = 0
        if self._reset_phase:
            if state is PowerState.FAULT or self._reset_phase == 2:
                command = CW_DISABLE_VOLTAGE if self._reset_phase == 1 else CW_FAULT_RESET
                self._reset_phase = 2 if self._reset_phase == 1 else 0
                return self._send(command, None)
            if state is PowerState.FAULT_REACTION_ACTIVE:
                # Its fault reaction (a torque ramp, 0x605E) is still under way: CiA 402 resets only
                # from FAULT, so the request waits for it rather than being lost.
                return self._send(CW_DISABLE_VOLTAGE, None)
            self._reset_phase = 0  # nothing to reset any more
        if not want_torque or state in (None, PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
            timed_out = None
            if (
                state in (PowerState.OPERATION_ENABLED, PowerState.QUICK_STOP_ACTIVE)
                and self._command == CW_DISABLE_VOLTAGE
            ):
                # The safety-relevant direction: a drive that keeps its power stage on after
                # "disable voltage" is reported like one that does not enable.
                timed_out = self._count_wait(state, CW_DISABLE_VOLTAGE) if fresh else None
            return self._send(CW_DISABLE_VOLTAGE, timed_out)
        wanted = _towards_torque(state)
        timed_out = None
        if state is not PowerState.OPERATION_ENABLED and wanted == self._command and fresh:
            timed_out = self._count_wait(state, wanted)
        return self._send(wanted, timed_out)

    def _count_wait(self, state: PowerState, command: int) -> str | None:
        """One more tick in ``state`` after ``command``; the report once it waited past the timeout."""
        self._waited += 1
        if self._waited <= self.timeout_ticks:
            return None
        report = (
            f"the drive stayed in {state.value} for {self._waited} ticks after controlword "
            f"0x{command:04X} (limit {self.timeout_ticks})"
        )
        self._waited = 0
        return report

    def _send(self, command: int, timed_out: str | None) -> StepOutcome:
        if command != self._command:
            self._waited = 0
        self._command = command
        if timed_out is None:
            quiet = _QUIET_OUTCOMES.get(command)
            if quiet is None:
                quiet = _QUIET_OUTCOMES[command] = StepOutcome(command)
            return quiet
        return StepOutcome(command, timed_out)
