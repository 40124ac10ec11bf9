"""``fsm_spec.yaml``: the schema of the safety FSM, its loader and the checks a spec must pass.

The spec declares the states in advance order (numbered 1..N), the superstate each belongs to,
what the robot may do in it (a control mode from :data:`~daror_runtime.fsm.modes.MODES`, a motor
torque limit and a joint velocity limit), whether a fault enters FAIL from it, and the named
guards (from :data:`~daror_runtime.fsm.guards.GUARDS`) of its advance, revert and reset
transitions; and the FAIL state with the guards of the reset that leaves it.

Loading is two passes: pydantic checks the shape and the types (strict: a bool or a string where
a number is meant is refused; the file itself is read by :func:`hal.yamlfile.read_yaml`, which
refuses duplicate keys, aliases, tags, deep nesting and anything that is not a small regular
file); :func:`check_spec` checks the meaning (names registered, numbering, hierarchy) and the
safety invariants of the spec itself (:data:`INVARIANTS`: torque and speed limits within the
device's, no torque in the first state nor before the e-stops were tested, test states consistent
with their modes, FAIL left only after the fault is cleared and acknowledged, position control and
torque inside the pilot's ISB limits, only approved models compensate; docs/fsm.md has the
table). Every problem is reported with the file, the line and the field, all problems at once,
and the runtime refuses to start on any.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError
from pydantic_core import PydanticCustomError

from daror_runtime.errors import InputError
from daror_runtime.fsm.guards import ARM_RELEASED_GUARD, FAIL_RESET_GUARDS, GUARDS
from daror_runtime.fsm.modes import MODES, ModeInfo
from daror_runtime.safety.faults import FaultKind
from hal.robot import MAX_RELAY_DELAY_S, RobotDescription, load_description
from hal.yamlfile import Flag, Integer, Number, format_validation_error, line_of, read_yaml

__all__ = [
    "DEFAULT_SPEC_PATH",
    "INVARIANTS",
    "FsmSpec",
    "FsmSpecError",
    "Invariant",
    "StateSpec",
    "check_spec",
    "load_fsm_spec",
    "spec_json_schema",
]

#: The spec at the repository root (docs/fsm.md).
DEFAULT_SPEC_PATH = Path(__file__).resolve().parents[2] / "fsm_spec.yaml"
SCHEMA_PATH = DEFAULT_SPEC_PATH.with_name("fsm_spec.schema.json")


class FsmSpecError(InputError):
    """The FSM spec is missing, not YAML, or wrong; the message names file, line and field."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


StateName = Annotated[
    str,
    Field(pattern=r"^[a-z][a-z0-9_]*$", description="lower-case identifier, e.g. safety_check"),
]
GuardName = Annotated[str, Field(json_schema_extra={"enum": sorted(GUARDS)}, description="a registered guard")]
ModeName = Annotated[str, Field(json_schema_extra={"enum": sorted(MODES)}, description="a registered control mode")]


class SuperstateSpec(_Strict):
    name: StateName
    description: str = ""


class StateLimits(_Strict):
    """What the safety filter and monitor enforce in the state (on top of the device's own limits)."""

    torque_nm: Number = Field(ge=0.0, le=1000.0, description="largest motor torque command, Nm (0: no torque)")
    velocity_rad_s: Number = Field(
        gt=0.0, le=100.0, description="largest joint speed, rad/s (the device's own limits apply too)"
    )


class Guards(_Strict):
    advance: list[GuardName] = Field(default_factory=list, description="all must hold, plus the operator's press")
    revert: list[GuardName] = Field(default_factory=list, description="all must hold to step back one state")
    reset: list[GuardName] = Field(default_factory=list, description="all must hold to reset to the first state")


class StateSpec(_Strict):
    number: Integer = Field(ge=1, description="position in advance order, 1..N without gaps")
    name: StateName
    superstate: StateName
    description: str = ""
    mode: ModeName
    limits: StateLimits
    fail_on_fault: Flag = Field(description="a fault enters FAIL (false only in the e-stop test states)")
    enforce_isb: Flag = Field(False, description="the pilot's recorded ISB limits are enforced in this state")
    guards: Guards = Field(default_factory=Guards)

    @property
    def label(self) -> str:
        return f"{self.number} {self.name}"


class FailGuards(_Strict):
    reset: list[GuardName] = Field(description=f"must include {', '.join(FAIL_RESET_GUARDS)}")


#: What a fault makes the robot do (docs/safety.md, "Fault reactions"; IEC 60204-1 stop categories):
#: ``off`` category 0, torque off now; ``lower`` category 1, hold the pose under gravity support, lower
#: the arm at a bounded speed to the rest pose of the session settings, hand it to its rest, then
#: torque off; ``hold`` category 2, hold the pose under gravity support until the operator acts.
def _quoted_off(value: object) -> object:
    """Refuse a YAML boolean where a reaction is meant: YAML 1.1 reads a bare ``off`` (or ``no``) as false."""
    if isinstance(value, bool):
        raise PydanticCustomError(
            "reaction_unquoted",
            'YAML reads a bare off (or no, false) as a yes/no value: write "off" in quotes',
        )
    return value


Reaction = Annotated[Literal["off", "lower", "hold"], BeforeValidator(_quoted_off)]

#: Fault kinds whose fault means that the joint it names cannot be trusted: its drive (drive), its
#: torque path (torque, deflection: the spring at or near its end stop) or its sensors (not_finite,
#: jump). That joint's torque must go off (category 0 for it) whatever the rest of the arm does.
UNTRUSTED_JOINT_KINDS: tuple[FaultKind, ...] = (
    FaultKind.DRIVE,
    FaultKind.TORQUE,
    FaultKind.DEFLECTION,
    FaultKind.NOT_FINITE,
    FaultKind.JUMP,
)
#: Fault kinds after which the runtime has no fresh reading of any joint: nothing can be controlled.
BLIND_KINDS: tuple[FaultKind, ...] = (FaultKind.STALE,)
#: Fault kinds that may come from the compensation model itself (a controller or the model failed):
#: a reaction must not lean on that model.
MODEL_SUSPECT_KINDS: tuple[FaultKind, ...] = (FaultKind.SOFTWARE,)
#: The longest a drive may ramp its torque down by itself once it lost the master, s.
MAX_DRIVE_RAMP_S = 10.0


class FaultReaction(_Strict):
    """What a fault of one kind commands (``fault_reactions`` of the spec)."""

    reaction: Reaction = Field(
        description="off: torque off now (category 0); lower: hold, lower to the rest pose, hand the arm to its "
        "rest, torque off (category 1); hold: hold under gravity support until the operator acts (category 2)"
    )
    faulted_joint: Annotated[Literal["off", "with_the_arm"], BeforeValidator(_quoted_off)] = Field(
        "with_the_arm",
        description="off: the joint the fault names gets no torque (its drive or sensors cannot be trusted), the "
        "others react as declared; with_the_arm: it reacts with the others",
    )
    support: Literal["model", "a_priori"] = Field(
        "model",
        description="the gravity support a hold or lowering uses: the model in use (approved for the pilot), or "
        "the A Priori model (when the fault may come from the model)",
    )
    within_s: Annotated[Number, Field(gt=0.0, le=MAX_RELAY_DELAY_S)] | None = Field(
        None, description="estop only, with lower (an ss1 wiring): the controlled stop ends with torque off within this"
    )
    states: dict[StateName, Reaction] = Field(
        default_factory=dict, description="state name -> the reaction in that state, where it must differ"
    )

    def in_state(self, state: str) -> Reaction:
        """The reaction in ``state`` (its override, else the kind's)."""
        return self.states.get(state, self.reaction)


class DriveReactionSpec(_Strict):
    """What every drive does by itself when it loses the master (a crashed runtime, a cut bus)."""

    reaction: Annotated[Literal["off", "ramp"], BeforeValidator(_quoted_off)] = Field(
        description="off: each drive disables at once (category 0); ramp: each ramps its torque to zero over "
        "ramp_s, then disables (category 1, done by the drive)"
    )
    ramp_s: Annotated[Number, Field(gt=0.0, le=MAX_DRIVE_RAMP_S)] | None = Field(
        None, description="ramp only: how long the drive takes to bring its torque from the last target to zero, s"
    )


class DriveReactions(_Strict):
    """The drives' own reactions (the CANopen backend configures them at start-up, docs/canopen.md)."""

    master_lost: DriveReactionSpec


class FailSpec(_Strict):
    name: Annotated[str, Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$")] = "FAIL"
    description: str = ""
    mode: ModeName = "torque_off"
    guards: FailGuards

    @property
    def label(self) -> str:
        return self.name


def _whole_number(value: object) -> object:
    """Refuse a bool or a float where a whole number is meant (``Literal[1]`` alone takes ``true`` and ``1.0``)."""
    if isinstance(value, bool | float):
        raise PydanticCustomError("int_type", "Input should be a whole number")
    return value


class FsmSpec(_Strict):
    """The whole spec (``fsm_spec.yaml``)."""

    version: Annotated[Literal[1], BeforeValidator(_whole_number)]
    superstates: list[SuperstateSpec] = Field(min_length=1)
    states: list[StateSpec] = Field(min_length=1)
    fail: FailSpec
    fault_reactions: dict[FaultKind, FaultReaction] = Field(
        description="fault kind -> what a fault of that kind commands (every kind listed)"
    )
    drive_reactions: DriveReactions

    @property
    def first(self) -> StateSpec:
        return self.states[0]

    def state(self, name: str) -> StateSpec:
        """The state called ``name`` (not FAIL). Raises KeyError."""
        for state in self.states:
            if state.name == name:
                return state
        raise KeyError(name)

    def next_state(self, state: StateSpec) -> StateSpec | None:
        return self.states[state.number] if state.number < len(self.states) else None

    def previous_state(self, state: StateSpec) -> StateSpec | None:
        return self.states[state.number - 2] if state.number > 1 else None

    @property
    def test_states(self) -> tuple[StateSpec, ...]:
        """States where a fault does not enter FAIL (the e-stop test states)."""
        return tuple(s for s in self.states if not s.fail_on_fault)


Location = tuple[int | str, ...]


@dataclass(frozen=True)
class Invariant:
    """A safety invariant of the spec itself: what must hold, and why (docs/fsm.md has the table)."""

    name: str
    rule: str
    why: str


#: Every safety invariant :func:`check_spec` enforces; a violation's message ends ``[safety invariant: NAME]``.
INVARIANTS: dict[str, Invariant] = {
    i.name: i
    for i in (
        Invariant(
            "torque limit fits the mode",
            "a state's torque limit is 0 exactly when its mode applies no torque",
            "a limit above 0 in a torque-free state misstates what the state allows; a torque mode at 0 Nm cannot do its job",
        ),
        Invariant(
            "torque within the drive",
            "no state's torque limit exceeds the drive's maximum motor torque (robot description sea.max_motor_torque_nm)",
            "a limit the drives can never reach is no limit: the spec would promise a cap the safety filter never applies",
        ),
        Invariant(
            "speed within the device",
            "no state's velocity limit exceeds the fastest joint speed the device allows (limits.max_velocity_rad_s)",
            "a limit above every joint's device limit never acts: the device's limit is what holds, not the spec's",
        ),
        Invariant(
            "first state torque-free",
            "the first state (entered at start-up and by every reset) applies no torque",
            "after a reset nothing about the session is known (faults, e-stops, the pilot); the drives stay off",
        ),
        Invariant(
            "e-stops tested before torque",
            "no state before the first e-stop test state applies torque",
            "torque is applied only once the e-stops were shown to remove it",
        ),
        Invariant(
            "test states are pilot-driven",
            "an e-stop test state (fail_on_fault: false) uses a mode that applies torque and is pilot-driven",
            "there must be torque for the e-stop to remove, and no motion the robot starts on its own while a fault "
            "does not enter FAIL",
        ),
        Invariant(
            "test states test an e-stop",
            "an e-stop test state's advance requires an e-stop test guard; a state that enters FAIL on a fault lists none",
            "a state that does not fail on faults is only safe as a test; in a failing state the press fails instead of "
            "being recorded, so the guard could never hold",
        ),
        Invariant(
            "test states end released",
            "an e-stop test state's advance requires estop_released",
            "the next state must not start with a button still pressed (torque off, and released the moment it is let go)",
        ),
        Invariant(
            "FAIL removes torque",
            "FAIL's mode applies no torque",
            "FAIL's own mode holds nothing: what the arm gets in FAIL is the fault's reaction alone",
        ),
        Invariant(
            "FAIL left only when cleared and acknowledged",
            "FAIL's reset requires faults_cleared and fault_acknowledged",
            "the robot restarts only once the fault's condition is gone and the operator has seen it",
        ),
        Invariant(
            "position control inside the ISB limits",
            "a mode that moves the robot on its own (identification, hold) runs only with enforce_isb: true",
            "position control can drive the pilot's arm; the pilot's recorded range of motion must bound it",
        ),
        Invariant(
            "ISB limits recorded before enforced",
            "a state enforces the ISB limits only after a state whose advance requires isb_limits_recorded",
            "enforcing limits nobody recorded enforces the placeholder defaults, not the pilot's range",
        ),
        Invariant(
            "ISB limits entered with the arm inside",
            "a transition from a state that does not enforce the ISB limits into one that does requires "
            "arm_inside_isb_limits",
            "the state enforces them from its first tick: an arm outside them is an ISB fault the moment it is "
            "entered (issue 24, defect 3)",
        ),
        Invariant(
            "ISB limits stay enforced",
            "after the advance that requires isb_limits_recorded, every state that applies torque enforces the ISB limits",
            "once the pilot's range is known, no torque may move the arm outside it",
        ),
        Invariant(
            "FAIL left only with the arm released",
            "FAIL's reset requires arm_released",
            "a reset enters the first state, which applies no torque: an arm the reaction still holds would drop",
        ),
        Invariant(
            "every fault has a reaction",
            "fault_reactions lists every fault kind, and names only states of the spec",
            "a fault nobody declared a reaction for would be met by a guess; a state override for a state that does "
            "not exist is a typo that silently keeps the kind's reaction",
        ),
        Invariant(
            "untrusted joints get no torque",
            "a fault of a joint's drive, torque path or sensors (drive, torque, deflection, not_finite, jump) takes "
            "that joint's torque off (faulted_joint: off)",
            "torque on a joint whose drive, spring or encoders cannot be trusted is torque nobody controls",
        ),
        Invariant(
            "no reaction without fresh readings",
            "a fault that leaves no fresh reading of any joint (stale) is met with off, in every state",
            "holding or lowering needs the arm's pose every tick; without it the controller would act on the past",
        ),
        Invariant(
            "e-stops stop in category 0 or 1",
            "the e-stop's reaction is off, or lower with within_s (only where the robot's buttons are wired for a "
            "safe stop 1 whose relay gives the runtime at least that long); never hold",
            "an e-stop must end with the torque off, at once or after a bounded controlled stop (IEC 60204-1)",
        ),
        Invariant(
            "no reaction leans on a suspect model",
            "a fault that may come from the compensation model (software) holds or lowers with the A Priori model "
            "(support: a_priori)",
            "a model that may have caused the fault is not trusted to hold the arm while the robot stops",
        ),
        Invariant(
            "reactions hold only what the robot held",
            "a state override in a state whose mode applies no torque is off",
            "where the drives are off the robot holds nothing; a reaction that switched torque on there would move "
            "an arm nobody asked it to",
        ),
        Invariant(
            "only approved models compensate",
            "every way into a state whose mode applies a compensation model is guarded by compensation_model_approved "
            "or model_trained_and_validated, and the first state applies no model",
            "a model nobody approved for this pilot never drives the arm",
        ),
    )
}


def _violates(name: str, message: str) -> str:
    """``message`` naming the invariant it breaks."""
    if name not in INVARIANTS:  # a programming error: every message names a declared invariant
        raise KeyError(name)
    return f"{message} [safety invariant: {name}]"


@cache
def _packaged_description() -> RobotDescription:
    return load_description()


def _problems(spec: FsmSpec) -> Iterator[tuple[Location, str]]:
    """Everything wrong with the structure of ``spec`` and its invariants: (location of the field, message).

    One function per family of check, in this order (the order of the messages a user reads).
    """
    yield from _naming_problems(spec)
    yield from _numbering_problems(spec)
    yield from _hierarchy_problems(spec)
    yield from _states_problems(spec)
    yield from _isb_entry_problems(spec)
    yield from _model_approval_problems(spec)
    yield from _reaction_problems(spec)
    yield from _fail_problems(spec)


def _first_index_of_number(spec: FsmSpec) -> dict[int, int]:
    """Per state number, the index of the first state listed with it."""
    numbers: dict[int, int] = {}
    for i, state in enumerate(spec.states):
        numbers.setdefault(state.number, i)
    return numbers


def _naming_problems(spec: FsmSpec) -> Iterator[tuple[Location, str]]:
    """Names and numbers used once: superstates, states, and no state named like a superstate or FAIL."""
    superstates = [s.name for s in spec.superstates]
    for k, name in enumerate(superstates):
        if name in superstates[:k]:
            yield ("superstates", k, "name"), f"superstate {name!r} is declared twice"
    names: dict[str, int] = {}
    numbers: dict[int, int] = {}
    for i, state in enumerate(spec.states):
        if state.name in names:
            yield ("states", i, "name"), f"state name {state.name!r} is used twice (also states.{names[state.name]})"
        names.setdefault(state.name, i)
        if state.number in numbers:
            yield (
                ("states", i, "number"),
                f"state number {state.number} is used twice (also states.{numbers[state.number]})",
            )
        numbers.setdefault(state.number, i)
        if state.name in superstates:
            yield ("states", i, "name"), f"state name {state.name!r} is also a superstate's name"
        if state.name == spec.fail.name:
            yield ("states", i, "name"), f"state name {state.name!r} is the FAIL state's name"


def _numbering_problems(spec: FsmSpec) -> Iterator[tuple[Location, str]]:
    """Advance order: 1..N in the order listed; a gap leaves every state after it unreachable."""
    numbers = _first_index_of_number(spec)
    for i, state in enumerate(spec.states):
        expected = i + 1
        if state.number == expected or numbers.get(state.number) != i:
            continue  # in place, or a duplicate number (reported by _naming_problems)
        if expected not in numbers:
            yield (
                ("states", i, "number"),
                f"state {state.label} is unreachable by advance: no state is numbered {expected}",
            )
        else:
            yield (
                ("states", i, "number"),
                f"state {state.label} is listed as state {expected}; list the states in advance order 1..N",
            )


def _hierarchy_problems(spec: FsmSpec) -> Iterator[tuple[Location, str]]:
    """Hierarchy: every superstate declared, used, and its states consecutive."""
    superstates = [s.name for s in spec.superstates]
    seen: list[str] = []
    for i, state in enumerate(spec.states):
        if state.superstate not in superstates:
            yield (
                ("states", i, "superstate"),
                f"superstate {state.superstate!r} is not declared (declared: {', '.join(superstates)})",
            )
        elif seen and state.superstate != seen[-1] and state.superstate in seen:
            yield (
                ("states", i, "superstate"),
                f"state {state.label} returns to superstate {state.superstate!r}; a superstate's states must be consecutive",
            )
        if not seen or seen[-1] != state.superstate:
            seen.append(state.superstate)
    for k, name in enumerate(superstates):
        if name not in seen:
            yield ("superstates", k, "name"), f"superstate {name!r} has no state"


def _states_problems(spec: FsmSpec) -> Iterator[tuple[Location, str]]:
    """Each state's mode, guards and limits, state by state (all of one state's problems together)."""
    isb_recorded_before = False  # whether an earlier state's advance requires isb_limits_recorded
    last = len(spec.states) - 1
    for i, state in enumerate(spec.states):
        yield from _state_problems(i, state, last, isb_recorded_before)
        if "isb_limits_recorded" in state.guards.advance:
            isb_recorded_before = True


def _state_problems(i: int, state: StateSpec, last: int, isb_recorded_before: bool) -> Iterator[tuple[Location, str]]:
    """State ``i``'s mode, guards and limits; ``last`` the last state's index, ``isb_recorded_before``
    whether an earlier state's advance requires isb_limits_recorded."""
    mode = MODES.get(state.mode)
    if mode is None:
        yield ("states", i, "mode"), f"unknown mode {state.mode!r}; expected one of {', '.join(MODES)}"
    yield from _guard_list_problems(i, state, last)
    if mode is not None:
        yield from _torque_limit_problems(i, state, mode)
        yield from _test_state_mode_problems(i, state, mode)
        yield from _isb_enforced_problems(i, state, mode, isb_recorded_before)
    yield from _estop_test_problems(i, state, last)
    if state.enforce_isb and not isb_recorded_before:
        yield (
            ("states", i, "enforce_isb"),
            _violates(
                "ISB limits recorded before enforced",
                f"state {state.label} enforces the ISB limits but no earlier state's advance requires "
                "isb_limits_recorded",
            ),
        )


def _guard_list_problems(i: int, state: StateSpec, last: int) -> Iterator[tuple[Location, str]]:
    """State ``i``'s guards: registered, listed once, and none on a transition the state does not have."""
    for kind in ("advance", "revert", "reset"):
        listed: list[str] = getattr(state.guards, kind)
        for j, name in enumerate(listed):
            if name not in GUARDS:
                yield (
                    ("states", i, "guards", kind, j),
                    f"unknown guard {name!r}; expected one of {', '.join(GUARDS)}",
                )
            elif name in listed[:j]:
                yield ("states", i, "guards", kind, j), f"guard {name!r} is listed twice"
    if i == 0 and state.guards.revert:
        yield (
            ("states", i, "guards", "revert"),
            f"state {state.label} is the first state: it has no revert, so revert guards would never be used",
        )
    if i == last and state.guards.advance:
        yield (
            ("states", i, "guards", "advance"),
            f"state {state.label} is the last state: it has no advance, so advance guards would never be used",
        )


def _torque_limit_problems(i: int, state: StateSpec, mode: ModeInfo) -> Iterator[tuple[Location, str]]:
    """State ``i``'s torque limit fits its mode: 0 exactly when the mode applies no torque."""
    if mode.applies_torque and state.limits.torque_nm == 0.0:
        yield (
            ("states", i, "limits", "torque_nm"),
            _violates(
                "torque limit fits the mode",
                f"state {state.label}: mode {mode.name!r} applies torque but the torque limit is 0",
            ),
        )
    if not mode.applies_torque and state.limits.torque_nm != 0.0:
        yield (
            ("states", i, "limits", "torque_nm"),
            _violates(
                "torque limit fits the mode",
                f"state {state.label}: mode {mode.name!r} applies no torque; its torque limit must be 0, not "
                f"{state.limits.torque_nm:g}",
            ),
        )


def _test_state_mode_problems(i: int, state: StateSpec, mode: ModeInfo) -> Iterator[tuple[Location, str]]:
    """State ``i``, when an e-stop test state (no FAIL on a fault), has a pilot-driven mode that applies torque."""
    if not state.fail_on_fault and not (mode.applies_torque and mode.pilot_driven):
        yield (
            ("states", i, "fail_on_fault"),
            _violates(
                "test states are pilot-driven",
                f"state {state.label} does not enter FAIL on a fault (an e-stop test state) but its mode "
                f"{mode.name!r} "
                + (
                    "applies no torque for the e-stop to remove"
                    if not mode.applies_torque
                    else "moves the robot on its own"
                )
                + "; a test state needs a pilot-driven mode that applies torque",
            ),
        )


def _isb_enforced_problems(
    i: int, state: StateSpec, mode: ModeInfo, isb_recorded_before: bool
) -> Iterator[tuple[Location, str]]:
    """State ``i`` enforces the ISB limits where its mode needs it: position control always, any torque
    once the limits were recorded (``isb_recorded_before``)."""
    if mode.applies_torque and not mode.pilot_driven and not state.enforce_isb:
        what = (
            "the identification protocol must run"
            if state.mode == "identification"
            else f"mode {mode.name!r} moves the robot on its own (position control) and must stay"
        )
        yield (
            ("states", i, "enforce_isb"),
            _violates(
                "position control inside the ISB limits",
                f"state {state.label}: {what} inside the pilot's ISB limits (enforce_isb: true)",
            ),
        )
    elif mode.applies_torque and isb_recorded_before and not state.enforce_isb:
        yield (
            ("states", i, "enforce_isb"),
            _violates(
                "ISB limits stay enforced",
                f"state {state.label} applies torque after the pilot's ISB limits were recorded but does not "
                "enforce them (enforce_isb: true)",
            ),
        )


def _estop_test_problems(i: int, state: StateSpec, last: int) -> Iterator[tuple[Location, str]]:
    """State ``i`` is an e-stop test state (tests an e-stop, ends released) exactly when it does not fail on a fault."""
    estop_guards = [g for g in state.guards.advance if g in GUARDS and GUARDS[g].estop_test]
    if not state.fail_on_fault and not estop_guards:
        yield (
            ("states", i, "guards", "advance"),
            _violates(
                "test states test an e-stop",
                f"state {state.label} does not enter FAIL on a fault, so it must be an e-stop test: its advance "
                "guards need one of " + ", ".join(g.name for g in GUARDS.values() if g.estop_test),
            ),
        )
    if not state.fail_on_fault and i != last and "estop_released" not in state.guards.advance:
        yield (
            ("states", i, "guards", "advance"),
            _violates(
                "test states end released",
                f"state {state.label} is an e-stop test state: its advance guards need estop_released, so the "
                "next state does not start with a button pressed",
            ),
        )
    if state.fail_on_fault and estop_guards:
        yield (
            ("states", i, "fail_on_fault"),
            _violates(
                "test states test an e-stop",
                f"state {state.label} enters FAIL on a fault, so an e-stop press fails instead of being recorded: "
                f"its advance guard {estop_guards[0]!r} could never hold (set fail_on_fault: false to make it a "
                "test state)",
            ),
        )


def _fail_problems(spec: FsmSpec) -> Iterator[tuple[Location, str]]:
    """The FAIL state: it removes torque, and its reset is guarded (cleared, acknowledged, arm released)."""
    fail_mode = MODES.get(spec.fail.mode)
    if fail_mode is None:
        yield ("fail", "mode"), f"unknown mode {spec.fail.mode!r}; expected one of {', '.join(MODES)}"
    elif fail_mode.applies_torque:
        yield (
            ("fail", "mode"),
            _violates(
                "FAIL removes torque",
                f"the FAIL state must remove torque; mode {fail_mode.name!r} applies torque",
            ),
        )
    for j, name in enumerate(spec.fail.guards.reset):
        if name not in GUARDS:
            yield ("fail", "guards", "reset", j), f"unknown guard {name!r}; expected one of {', '.join(GUARDS)}"
    missing = [g for g in FAIL_RESET_GUARDS if g not in spec.fail.guards.reset]
    if missing:
        yield (
            ("fail", "guards", "reset"),
            _violates(
                "FAIL left only when cleared and acknowledged",
                f"FAIL must be left only after the fault is cleared and acknowledged: add {', '.join(missing)}",
            ),
        )
    if ARM_RELEASED_GUARD not in spec.fail.guards.reset:
        yield (
            ("fail", "guards", "reset"),
            _violates(
                "FAIL left only with the arm released",
                "FAIL's reset enters the first state, which applies no torque: add arm_released, so a reset never "
                "drops an arm the fault's reaction still holds",
            ),
        )


def _reaction_problems(spec: FsmSpec) -> Iterator[tuple[Location, str]]:
    """The fault reactions: complete, and each safe for what its fault means."""
    missing = [kind.value for kind in FaultKind if kind not in spec.fault_reactions]
    if missing:
        yield (
            ("fault_reactions",),
            _violates(
                "every fault has a reaction",
                f"no reaction for the fault kind(s) {', '.join(missing)}; list every kind "
                f"({', '.join(k.value for k in FaultKind)})",
            ),
        )
    names = {state.name: state for state in spec.states}
    for kind, entry in spec.fault_reactions.items():
        where: Location = ("fault_reactions", kind.value)
        for name, reaction in entry.states.items():
            state = names.get(name)
            if state is None:
                yield (
                    (*where, "states", name),
                    _violates(
                        "every fault has a reaction",
                        f"{kind.value}: no state is called {name!r}; expected one of {', '.join(names)}",
                    ),
                )
                continue
            mode = MODES.get(state.mode)
            if mode is not None and not mode.applies_torque and reaction != "off":
                yield (
                    (*where, "states", name),
                    _violates(
                        "reactions hold only what the robot held",
                        f"{kind.value} in state {state.label}: mode {mode.name!r} applies no torque, so the robot "
                        f"holds nothing there to {reaction}; expected off",
                    ),
                )
        if kind in UNTRUSTED_JOINT_KINDS and entry.faulted_joint != "off":
            yield (
                (*where, "faulted_joint"),
                _violates(
                    "untrusted joints get no torque",
                    f"a {kind.value} fault means its joint's drive, torque path or sensors cannot be trusted: "
                    "expected faulted_joint: off",
                ),
            )
        if kind in BLIND_KINDS:
            for state, reaction in (("", entry.reaction), *entry.states.items()):
                if reaction != "off":
                    yield (
                        (*where, "states", state) if state else (*where, "reaction"),
                        _violates(
                            "no reaction without fresh readings",
                            f"a {kind.value} fault leaves no fresh reading of any joint"
                            + (f" (in state {state})" if state else "")
                            + f": nothing can {reaction} the arm without them; expected off",
                        ),
                    )
        if kind in MODEL_SUSPECT_KINDS and entry.support != "a_priori" and entry.reaction != "off":
            yield (
                (*where, "support"),
                _violates(
                    "no reaction leans on a suspect model",
                    f"a {kind.value} fault may come from the compensation model: expected support: a_priori",
                ),
            )
        if kind == FaultKind.ESTOP:
            for state, reaction in (("", entry.reaction), *entry.states.items()):
                if reaction == "hold":
                    yield (
                        (*where, "states", state) if state else (*where, "reaction"),
                        _violates(
                            "e-stops stop in category 0 or 1",
                            "an e-stop must end with the torque off: expected off or lower (with within_s), not hold",
                        ),
                    )
                elif reaction == "lower" and entry.within_s is None:
                    yield (
                        (*where, "within_s"),
                        _violates(
                            "e-stops stop in category 0 or 1",
                            "an e-stop that lowers the arm needs within_s: the bound within which the torque is off",
                        ),
                    )
        elif entry.within_s is not None:
            yield (*where, "within_s"), f"{kind.value}: within_s belongs to the e-stop's reaction only"
    drive = spec.drive_reactions.master_lost
    if (drive.reaction == "ramp") != (drive.ramp_s is not None):
        yield (
            ("drive_reactions", "master_lost", "ramp_s"),
            "master_lost: ramp needs ramp_s (how long the drive ramps its torque to zero) and off takes none",
        )


def _device_problems(spec: FsmSpec, description: RobotDescription) -> Iterator[tuple[Location, str]]:
    """The state limits against the device's own (the robot description)."""
    max_torque = description.sea.max_motor_torque_nm
    max_speed = max(description.limits.max_velocity_rad_s)
    for i, state in enumerate(spec.states):
        if state.limits.torque_nm > max_torque:
            yield (
                ("states", i, "limits", "torque_nm"),
                _violates(
                    "torque within the drive",
                    f"state {state.label}: torque limit {state.limits.torque_nm:g} Nm exceeds the drives' maximum motor "
                    f"torque of the {description.name}, {max_torque:g} Nm (robot description sea.max_motor_torque_nm); "
                    f"expected at most {max_torque:g}",
                ),
            )
        if state.limits.velocity_rad_s > max_speed:
            yield (
                ("states", i, "limits", "velocity_rad_s"),
                _violates(
                    "speed within the device",
                    f"state {state.label}: velocity limit {state.limits.velocity_rad_s:g} rad/s exceeds every joint's "
                    f"speed limit of the {description.name} (at most {max_speed:g} rad/s, robot description "
                    "limits.max_velocity_rad_s), so it would never act; expected at most "
                    f"{max_speed:g}",
                ),
            )


def _wiring_problems(spec: FsmSpec, description: RobotDescription) -> Iterator[tuple[Location, str]]:
    """The e-stop's reaction against how the robot's buttons are wired (robot description ``estop``)."""
    estop = spec.fault_reactions.get(FaultKind.ESTOP)
    if estop is None:
        return
    wiring = description.estop
    lowers = "lower" in (estop.reaction, *estop.states.values())
    if lowers and wiring.wiring == "sto":
        yield (
            ("fault_reactions", "estop", "reaction"),
            _violates(
                "e-stops stop in category 0 or 1",
                f"the e-stops of the {description.name} are wired to the drives' safe torque off (robot description "
                "estop.wiring: sto): a press removes the torque at once in hardware, so the runtime cannot lower the "
                "arm; expected off (or wire the buttons for a safe stop 1: estop.wiring: ss1)",
            ),
        )
    elif (
        lowers
        and estop.within_s is not None
        and wiring.relay_delay_s is not None
        and estop.within_s > wiring.relay_delay_s
    ):
        yield (
            ("fault_reactions", "estop", "within_s"),
            _violates(
                "e-stops stop in category 0 or 1",
                f"the e-stop's lowering may take {estop.within_s:g} s but the safety relay of the "
                f"{description.name} cuts the power {wiring.relay_delay_s:g} s after a press (robot description "
                f"estop.relay_delay_s); expected within_s at most {wiring.relay_delay_s:g}",
            ),
        )


def _order_problems(spec: FsmSpec) -> Iterator[tuple[Location, str]]:
    """No torque in the first state, and none before the e-stops are shown to work."""
    first = spec.states[0]
    first_mode = MODES.get(first.mode)
    if first_mode is not None and first_mode.applies_torque:
        yield (
            ("states", 0, "mode"),
            _violates(
                "first state torque-free",
                f"state {first.label} is the first state (entered at start-up and by every reset) but its mode "
                f"{first_mode.name!r} applies torque; expected a mode that applies none (torque_off)",
            ),
        )
    first_test = next((i for i, s in enumerate(spec.states) if not s.fail_on_fault), None)
    before = spec.states if first_test is None else spec.states[:first_test]
    for i, state in enumerate(before):
        mode = MODES.get(state.mode)
        if mode is None or not mode.applies_torque:
            continue
        where = (
            "no state tests the e-stops"
            if first_test is None
            else f"it comes before the first e-stop test state, {spec.states[first_test].label}"
        )
        yield (
            ("states", i, "mode"),
            _violates(
                "e-stops tested before torque",
                f"state {state.label}: mode {mode.name!r} applies torque but {where}; torque is applied only once "
                "the e-stops were shown to remove it",
            ),
        )


def _approves_model(guards: list[str]) -> bool:
    return any(g in GUARDS and GUARDS[g].approves_model for g in guards)


def _isb_entry_problems(spec: FsmSpec) -> Iterator[tuple[Location, str]]:
    """Advances and reverts that enter enforced ISB limits without ``arm_inside_isb_limits``.

    Only where the other ISB invariants hold: a state that enforces the limits before they are
    recorded, or one that applies torque after without enforcing them, is reported by those; the
    transitions around it would only repeat the same mistake.
    """
    states = spec.states
    recorded_at = next((k for k, s in enumerate(states) if "isb_limits_recorded" in s.guards.advance), None)
    if recorded_at is None:
        return
    for i, state in enumerate(states):
        mode = MODES.get(state.mode)
        if state.enforce_isb or (i > recorded_at and (mode is None or mode.applies_torque)):
            continue
        for event, j in (("advance", i + 1), ("revert", i - 1)):
            if not recorded_at < j < len(states) or not states[j].enforce_isb:
                continue
            if "arm_inside_isb_limits" not in getattr(state.guards, event):
                yield (
                    ("states", i, "guards", event),
                    _violates(
                        "ISB limits entered with the arm inside",
                        f"the {event} from {state.label} enters {states[j].label}, which enforces the ISB limits from "
                        "its first tick: its guards need arm_inside_isb_limits",
                    ),
                )


def _model_approval_problems(spec: FsmSpec) -> Iterator[tuple[Location, str]]:
    """A model nobody approved never drives the arm: every way into a state that applies a model is guarded."""
    approving = ", ".join(g.name for g in GUARDS.values() if g.approves_model)
    for i, state in enumerate(spec.states):
        mode = MODES.get(state.mode)
        if mode is None or not mode.applies_model:
            continue
        if i == 0:
            yield (
                ("states", i, "mode"),
                _violates(
                    "only approved models compensate",
                    f"state {state.label} is the first state (entered by every reset) but its mode {mode.name!r} "
                    "applies a compensation model, which nobody has approved when a session starts",
                ),
            )
            continue
        previous = spec.states[i - 1]
        if not _approves_model(previous.guards.advance):
            yield (
                ("states", i - 1, "guards", "advance"),
                _violates(
                    "only approved models compensate",
                    f"advancing from {previous.label} enters {state.label}, whose mode {mode.name!r} applies a "
                    f"compensation model: the advance guards need one that approves the model ({approving})",
                ),
            )
        following = spec.states[i + 1] if i + 1 < len(spec.states) else None
        if following is not None and not _approves_model(following.guards.revert):
            yield (
                ("states", i + 1, "guards", "revert"),
                _violates(
                    "only approved models compensate",
                    f"reverting from {following.label} enters {state.label}, whose mode {mode.name!r} applies a "
                    f"compensation model: the revert guards need one that approves the model ({approving})",
                ),
            )


def check_spec(
    spec: FsmSpec,
    source: str = "fsm spec",
    root: yaml.Node | None = None,
    description: RobotDescription | None = None,
) -> None:
    """Check the meaning of a parsed spec, its safety invariants (:data:`INVARIANTS`) included.

    ``description``: the robot whose drive and joint limits the state limits must respect
    (default: the packaged DAROR-01, ``hal/daror01.yaml``).

    Raises:
        FsmSpecError: one line per problem: ``source: line L, field a.b.c: message``.
    """
    device = description if description is not None else _packaged_description()
    lines = []
    problems = [
        *_problems(spec),
        *_device_problems(spec, device),
        *_wiring_problems(spec, device),
        *_order_problems(spec),
    ]
    for location, message in problems:
        line = line_of(root, location)
        where = f"line {line}, " if line is not None else ""
        field = ".".join(str(p) for p in location)
        lines.append(f"{source}: {where}field {field}: {message}")
    if lines:
        raise FsmSpecError("\n".join(lines))


def load_fsm_spec(path: Path | str | None = None, description: RobotDescription | None = None) -> FsmSpec:
    """Read, validate and check ``path`` (default: :data:`DEFAULT_SPEC_PATH`).

    ``description``: the robot the state limits are checked against (default: the packaged DAROR-01).

    Raises:
        FsmSpecError: the file is missing, not a regular file, not YAML, does not match the schema or
            fails a check; the message names the file, the line and the field of every problem.
    """
    path = Path(path) if path is not None else DEFAULT_SPEC_PATH
    data, root = read_yaml(path, FsmSpecError, expected="a mapping with version, superstates, states and fail")
    try:
        spec = FsmSpec.model_validate(data)
    except ValidationError as exc:
        raise FsmSpecError(format_validation_error(str(path), exc, root, separator="\n")) from None
    check_spec(spec, str(path), root, description)
    return spec


def spec_json_schema() -> dict[str, Any]:
    """The JSON Schema of ``fsm_spec.yaml`` (for editors: ``# yaml-language-server: $schema=...``)."""
    schema = FsmSpec.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "DAROR-01 safety FSM spec (fsm_spec.yaml)"
    return schema


def spec_json_schema_text() -> str:
    return json.dumps(spec_json_schema(), indent=2, sort_keys=True) + "\n"
