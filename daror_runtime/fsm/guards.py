"""The guard registry: every condition an ``fsm_spec.yaml`` may name, and what it reads.

A guard is a named, documented predicate over :class:`~daror_runtime.fsm.signals.SessionSignals`.
The spec refers to guards by name; :func:`daror_runtime.fsm.spec.load_fsm_spec` refuses a name
that is not registered here, so a typo is found when the spec is loaded, not when the operator
first presses Advance. The machine evaluates guards itself to name the unmet ones in a refusal.

Adding a guard: register it here with a description that reads as the condition that must hold
("the operator's e-stop was pressed in this state"); the description is what the operator sees
when the guard stops a transition.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from daror_runtime.fsm.signals import Checklist, EstopButton, SessionSignals
from daror_runtime.safety.monitor import isb_excess
from hal.interface import DriveState

GuardFunction = Callable[[SessionSignals], bool]


@dataclass(frozen=True)
class Guard:
    """A named condition.

    ``checklist``: the operator checklist whose confirmation this guard reads (the console accepts
    a confirmation only in a state whose advance guards need it).
    """

    name: str
    description: str
    read: GuardFunction
    checklist: Checklist | None = None
    estop_test: bool = False  # satisfied by pressing an e-stop in the state (a test state's evidence)
    approves_model: bool = False  # holds only when the compensation model in use is approved for the pilot
    explain: Callable[[SessionSignals], str | None] | None = None  # why it does not hold now, in figures


class BoundGuard:
    """A guard bound to the session's signals: call it for whether it holds, :meth:`why` for why not."""

    __slots__ = ("_guard", "_signals")

    def __init__(self, guard: Guard, signals: SessionSignals) -> None:
        self._guard = guard
        self._signals = signals

    def __call__(self) -> bool:
        return bool(self._guard.read(self._signals))

    def why(self) -> str | None:
        """What exactly is missing now (None: nothing more to say than the description)."""
        explain = self._guard.explain
        return explain(self._signals) if explain is not None else None


class GuardRegistry(Mapping[str, Guard]):
    """Name -> :class:`Guard`; read-only once the module is imported (register at import time)."""

    def __init__(self) -> None:
        self._guards: dict[str, Guard] = {}

    def register(
        self,
        name: str,
        description: str,
        *,
        checklist: Checklist | None = None,
        estop_test: bool = False,
        approves_model: bool = False,
        explain: Callable[[SessionSignals], str | None] | None = None,
    ) -> Callable[[GuardFunction], GuardFunction]:
        def add(read: GuardFunction) -> GuardFunction:
            if name in self._guards:
                raise ValueError(f"guard {name!r} registered twice")
            self._guards[name] = Guard(name, description, read, checklist, estop_test, approves_model, explain)
            return read

        return add

    def __getitem__(self, name: str) -> Guard:
        return self._guards[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._guards)

    def __len__(self) -> int:
        return len(self._guards)

    def bind(self, signals: SessionSignals) -> dict[str, Callable[[], bool]]:
        """Zero-argument predicates over ``signals``, by name (what the machine evaluates; :class:`BoundGuard`)."""
        return {name: BoundGuard(guard, signals) for name, guard in self._guards.items()}


GUARDS = GuardRegistry()
guard = GUARDS.register


# --- hardware and faults ---------------------------------------------------------------------


@guard("hal_connected", "the hardware delivers samples and no drive reports a fault")
def _hal_connected(s: SessionSignals) -> bool:
    return s.sample is not None and DriveState.FAULT not in s.sample.drives


@guard("no_active_faults", "no fault is latched")
def _no_active_faults(s: SessionSignals) -> bool:
    return s.monitor is not None and not s.monitor.faulted


@guard("faults_cleared", "the condition of every latched fault is gone")
def _faults_cleared(s: SessionSignals) -> bool:
    return s.monitor is not None and s.monitor.clearable


@guard("fault_acknowledged", "the operator acknowledged the fault")
def _fault_acknowledged(s: SessionSignals) -> bool:
    return s.fault_acknowledged


@guard("fault_latched", "a fault is latched (there is something to acknowledge)")
def _fault_latched(s: SessionSignals) -> bool:
    return s.monitor is not None and s.monitor.faulted


@guard(
    "arm_released",
    "no fault reaction holds the pilot's arm: it rests with the torque off, or the torque was off",
)
def _arm_released(s: SessionSignals) -> bool:
    return not s.arm_held


@guard("robot_at_rest", "every joint is at rest (slower than the session's at-rest speed)")
def _robot_at_rest(s: SessionSignals) -> bool:
    sample = s.sample
    return sample is not None and bool(np.all(np.abs(sample.dq_rad_s) < s.at_rest_rad_s))


# --- e-stop tests ----------------------------------------------------------------------------


@guard("estop_operator_tested", "the operator's e-stop was pressed in this state and removed torque", estop_test=True)
def _estop_operator_tested(s: SessionSignals) -> bool:
    return EstopButton.OPERATOR in s.estop_tested


@guard("estop_pilot_tested", "the pilot's e-stop was pressed in this state and removed torque", estop_test=True)
def _estop_pilot_tested(s: SessionSignals) -> bool:
    return EstopButton.PILOT in s.estop_tested


@guard(
    "estop_tested", "an e-stop (operator's or pilot's) was pressed in this state and removed torque", estop_test=True
)
def _estop_tested(s: SessionSignals) -> bool:
    return bool(s.estop_tested)


@guard("estop_released", "no e-stop is pressed")
def _estop_released(s: SessionSignals) -> bool:
    return s.sample is not None and True not in s.sample.estop


# --- the operator's checklists ---------------------------------------------------------------


@guard("settings_confirmed", "the operator confirmed the session settings", checklist=Checklist.SETTINGS)
def _settings_confirmed(s: SessionSignals) -> bool:
    return Checklist.SETTINGS in s.confirmed


@guard(
    "installation_confirmed",
    "the operator confirmed the installation checklist (straps, shoulder alignment, cables)",
    checklist=Checklist.INSTALLATION,
)
def _installation_confirmed(s: SessionSignals) -> bool:
    return Checklist.INSTALLATION in s.confirmed


@guard(
    "safety_experience_confirmed",
    "the operator confirmed that the pilot felt the safety limits",
    checklist=Checklist.SAFETY_EXPERIENCE,
)
def _safety_experience_confirmed(s: SessionSignals) -> bool:
    return Checklist.SAFETY_EXPERIENCE in s.confirmed


# --- the pilot's limits, data and models -----------------------------------------------------


@guard(
    "pilot_named",
    "the pilot is named by his code (pilot CODE, or the settings' pilot); a simulated robot's is its scenario's",
)
def _pilot_named(s: SessionSignals) -> bool:
    return s.pilot is not None or not s.drives_hardware


@guard("isb_limits_recorded", "the pilot's ISB limits are recorded")
def _isb_limits_recorded(s: SessionSignals) -> bool:
    return s.isb_limits is not None


def _isb_excess(s: SessionSignals) -> str | None:
    """How far the arm is outside the recorded ISB limits plus the margin (the worst angle); None: inside."""
    if s.isb_limits is None or s.isb_angles is None:
        return None
    if s.sample is None:
        return "no reading of the arm yet"
    return isb_excess(s.isb_angles(s.isb_limits)(s.sample.q_rad), s.isb_limits, s.isb_margin_rad)


@guard(
    "arm_inside_isb_limits",
    "the pilot's arm is inside his recorded ISB limits (with the margin the monitor allows): the next state "
    "enforces them from its first tick",
    explain=_isb_excess,
)
def _arm_inside_isb_limits(s: SessionSignals) -> bool:
    return _isb_excess(s) is None


@guard(
    "identification_data_or_model",
    "training and validation data of the identification protocol are saved, or a validated model is selected",
)
def _identification_data_or_model(s: SessionSignals) -> bool:
    saved = {"training", "validation"} <= s.identification_saved.keys()
    return saved or (s.model is not None and s.model.validated)


@guard(
    "model_trained_and_validated",
    "a model is selected whose validation error on this pilot's held-out data is within the session's limit",
    approves_model=True,
)
def _model_trained_and_validated(s: SessionSignals) -> bool:
    return s.model is not None and s.model.validated


@guard(
    "compensation_model_approved",
    "the compensation model is approved for this pilot: a model validated on the pilot's held-out data is "
    "selected, or the operator confirmed the A Priori model in this state",
    checklist=Checklist.A_PRIORI_MODEL,
    approves_model=True,
)
def _compensation_model_approved(s: SessionSignals) -> bool:
    return (s.model is not None and s.model.validated) or Checklist.A_PRIORI_MODEL in s.confirmed


#: Guards the machine itself uses (not named in specs): acknowledging needs something to acknowledge.
BUILT_IN_GUARDS = ("fault_latched",)
#: Guards FAIL's reset must list: FAIL is left only once the fault is gone and acknowledged.
FAIL_RESET_GUARDS = ("faults_cleared", "fault_acknowledged")
#: Guard FAIL's reset must list too: a reset enters the first state (no torque), so no reaction may still hold the arm.
ARM_RELEASED_GUARD = "arm_released"
