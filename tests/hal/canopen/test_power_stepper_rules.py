"""The master's CiA 402 power stepper (hal.canopen.cia402.statemachine.PowerStepper) against its rules.

:class:`PowerStepper.step` answers the step of nearly every tick of a session (torque wanted from a
drive in OPERATION ENABLED) before its general steps (issue 25). :class:`_Rules` is the class
docstring's rules written out here without that shortcut; random sequences of steps (any state,
wanted or not, fresh or not, fault reset requests) must give the same controlword and the same
report, tick by tick.
"""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from hal.canopen.cia402.statemachine import (
    CW_DISABLE_VOLTAGE,
    CW_ENABLE_OPERATION,
    CW_FAULT_RESET,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
    PowerState,
    PowerStepper,
)

_TOWARDS_TORQUE = {
    PowerState.OPERATION_ENABLED: CW_ENABLE_OPERATION,
    PowerState.SWITCHED_ON: CW_ENABLE_OPERATION,
    PowerState.SWITCH_ON_DISABLED: CW_SHUTDOWN,
    PowerState.READY_TO_SWITCH_ON: CW_SWITCH_ON,
    PowerState.NOT_READY_TO_SWITCH_ON: CW_DISABLE_VOLTAGE,
    PowerState.QUICK_STOP_ACTIVE: CW_DISABLE_VOLTAGE,
}
_FAULTS = (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE)


class _Rules:
    """The stepper's rules, from scratch: the reference."""

    def __init__(self, timeout_ticks: int) -> None:
        self.timeout_ticks = max(timeout_ticks, 2)
        self.command, self.waited, self.reset_phase = CW_DISABLE_VOLTAGE, 0, 0

    def step(self, state: PowerState | None, want: bool, fresh: bool) -> tuple[int, str | None]:
        if self.reset_phase == 2 and state is PowerState.FAULT_REACTION_ACTIVE:
            self.reset_phase = 0  # a new fault after the drive showed FAULT: the request is not spent on it
        if self.reset_phase:
            if state is PowerState.FAULT or self.reset_phase == 2:
                command = CW_DISABLE_VOLTAGE if self.reset_phase == 1 else CW_FAULT_RESET
                self.reset_phase = 2 if self.reset_phase == 1 else 0
                return self._send(command, None)
            if state is PowerState.FAULT_REACTION_ACTIVE:
                return self._send(CW_DISABLE_VOLTAGE, None)
            self.reset_phase = 0
        if not want or state is None or state in _FAULTS:
            late = None
            if state in (PowerState.OPERATION_ENABLED, PowerState.QUICK_STOP_ACTIVE) and self.command == 0 and fresh:
                late = self._count(state, CW_DISABLE_VOLTAGE)
            return self._send(CW_DISABLE_VOLTAGE, late)
        wanted = _TOWARDS_TORQUE[state]
        late = None
        if state is not PowerState.OPERATION_ENABLED and wanted == self.command and fresh:
            late = self._count(state, wanted)
        return self._send(wanted, late)

    def _count(self, state: PowerState, command: int) -> str | None:
        self.waited += 1
        if self.waited <= self.timeout_ticks:
            return None
        report = (
            f"the drive stayed in {state.value} for {self.waited} ticks after controlword "
            f"0x{command:04X} (limit {self.timeout_ticks})"
        )
        self.waited = 0
        return report

    def _send(self, command: int, late: str | None) -> tuple[int, str | None]:
        if command != self.command:
            self.waited = 0
        self.command = command
        return command, late


_states = st.one_of(st.none(), st.sampled_from(list(PowerState)))
# Mostly the session's steady tick (torque wanted, OPERATION ENABLED), with every other case mixed in
_tick = st.one_of(
    st.just((PowerState.OPERATION_ENABLED, True, True, False)),
    st.tuples(_states, st.booleans(), st.booleans(), st.booleans()),
)


@settings(max_examples=400, deadline=None)
@given(timeout_ticks=st.integers(0, 6), ticks=st.lists(_tick, min_size=1, max_size=120))
def test_every_step_gives_the_controlword_and_report_of_the_rules(
    timeout_ticks: int, ticks: list[tuple[PowerState | None, bool, bool, bool]]
) -> None:
    stepper, rules = PowerStepper(timeout_ticks), _Rules(timeout_ticks)
    for n, (state, want, fresh, reset) in enumerate(ticks):
        if reset:
            stepper.request_fault_reset()
            rules.reset_phase = 1
        outcome = stepper.step(state, want, fresh)
        assert (outcome.controlword, outcome.timed_out) == rules.step(state, want, fresh), (n, state, want, fresh)


def test_a_fault_reset_requested_while_enabled_is_dropped_not_kept_for_a_later_fault() -> None:
    stepper = PowerStepper(5)
    for state in (PowerState.SWITCH_ON_DISABLED, PowerState.READY_TO_SWITCH_ON, PowerState.SWITCHED_ON):
        stepper.step(state, True)
    assert stepper.step(PowerState.OPERATION_ENABLED, True).controlword == CW_ENABLE_OPERATION
    stepper.request_fault_reset()  # enabled, nothing to reset: the request is dropped, torque goes on
    assert stepper.step(PowerState.OPERATION_ENABLED, True).controlword == CW_ENABLE_OPERATION
    # A fault that comes later is not reset by that old request: nobody asked to reset this one
    assert [stepper.step(PowerState.FAULT, True).controlword for _ in range(3)] == [CW_DISABLE_VOLTAGE] * 3
    stepper.request_fault_reset()
    assert stepper.step(PowerState.FAULT, True).controlword == CW_DISABLE_VOLTAGE  # the edge: 0x00, then 0x80
    assert stepper.step(PowerState.FAULT, True).controlword == CW_FAULT_RESET


def test_a_fault_that_comes_between_the_request_and_its_edge_is_not_reset_by_it() -> None:
    """FAULT, the request's 0x00, then a fault reaction again: a new fault; the old request's 0x80 must not clear it."""
    stepper = PowerStepper(5)
    stepper.request_fault_reset()
    assert stepper.step(PowerState.FAULT, True).controlword == CW_DISABLE_VOLTAGE  # the edge's 0x00
    assert stepper.step(PowerState.FAULT_REACTION_ACTIVE, True).controlword == CW_DISABLE_VOLTAGE  # not 0x80
    assert [stepper.step(PowerState.FAULT, True).controlword for _ in range(3)] == [CW_DISABLE_VOLTAGE] * 3
    stepper.request_fault_reset()  # the operator acknowledges the new fault
    assert [stepper.step(PowerState.FAULT, True).controlword for _ in range(2)] == [CW_DISABLE_VOLTAGE, CW_FAULT_RESET]
