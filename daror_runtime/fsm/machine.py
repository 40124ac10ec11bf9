"""The safety machine: a ``transitions`` hierarchical state machine built from an :class:`FsmSpec`.

Events (Appendix A of the thesis; docs/fsm.md):

* ``advance``: to the next state, when the operator asks and every advance guard of the state holds;
* ``revert``: to the previous state, with the state's revert guards;
* ``reset``: to the first state, from every state (FAIL included), with the state's reset guards;
* ``fail``: to FAIL, automatic on a fault, from every state with ``fail_on_fault`` (never refused there);
* ``acknowledge``: the operator acknowledges a latched fault, in FAIL or in an e-stop test state
  (needed before reset may leave FAIL); an internal transition, the state does not change.

The ``transitions`` machine is built with no automatic ``to_<state>`` transitions, with invalid
triggers raising instead of being ignored, and queued, so a callback can never start a nested
transition. Each transition carries its guards as conditions. Before firing, :meth:`SafetyMachine.request`
looks the event up in its own table and evaluates the guards by name, so a refusal names what is
missing ("unmet: estop_pilot_tested (the pilot's e-stop was pressed in this state ...)"), and an
event with no transition from the current state is refused with the reason instead of raising.

The machine is pure logic: guards are zero-argument predicates handed in by name (the runtime
binds them to its session signals; the exhaustive test hands in forced outcomes); state entry is
reported to a callback (the supervisor switches the controller and limits there).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import NamedTuple

from transitions import MachineError
from transitions.extensions import HierarchicalMachine
from transitions.extensions.nesting import NestedState

from daror_runtime.errors import ConfigurationError
from daror_runtime.fsm.guards import GUARDS
from daror_runtime.fsm.spec import FailSpec, FsmSpec, StateSpec

__all__ = ["Event", "Outcome", "SafetyMachine", "Transition"]


class Event(StrEnum):
    ADVANCE = "advance"
    REVERT = "revert"
    RESET = "reset"
    FAIL = "fail"
    ACKNOWLEDGE = "acknowledge"


#: Events the operator may request (fail is the machine's own).
OPERATOR_EVENTS = (Event.ADVANCE, Event.REVERT, Event.RESET, Event.ACKNOWLEDGE)


class Outcome(NamedTuple):
    """What became of one event: accepted (and where to), or refused and why."""

    event: Event
    accepted: bool
    source: str
    dest: str | None  # the state after the event (the source for an internal transition); None if refused
    unmet: tuple[str, ...] = ()  # guards that did not hold
    reason: str = ""


@dataclass(frozen=True)
class Transition:
    """One row of the machine's table."""

    event: Event
    source: str
    dest: str  # == source for acknowledge (internal)
    guards: tuple[str, ...]

    @property
    def internal(self) -> bool:
        return self.event == Event.ACKNOWLEDGE


class _State(NestedState):
    # Our state names contain "_" (the library's default separator); "." never occurs in them.
    separator = "."


class _Machine(HierarchicalMachine):  # type: ignore[misc]
    state_cls = _State


class _Model:
    """The object ``transitions`` drives (it attaches ``state`` and the trigger methods)."""

    state: str


def transition_table(spec: FsmSpec) -> dict[tuple[str, Event], Transition]:
    """Every transition of ``spec``, keyed by (source state name, event)."""
    table: dict[tuple[str, Event], Transition] = {}
    first = spec.first.name
    fail = spec.fail.name
    for state in spec.states:
        following = spec.next_state(state)
        previous = spec.previous_state(state)
        if following is not None:
            table[(state.name, Event.ADVANCE)] = Transition(
                Event.ADVANCE, state.name, following.name, tuple(state.guards.advance)
            )
        if previous is not None:
            table[(state.name, Event.REVERT)] = Transition(
                Event.REVERT, state.name, previous.name, tuple(state.guards.revert)
            )
        table[(state.name, Event.RESET)] = Transition(Event.RESET, state.name, first, tuple(state.guards.reset))
        if state.fail_on_fault:
            table[(state.name, Event.FAIL)] = Transition(Event.FAIL, state.name, fail, ())
        else:
            table[(state.name, Event.ACKNOWLEDGE)] = Transition(
                Event.ACKNOWLEDGE, state.name, state.name, ("fault_latched",)
            )
    table[(fail, Event.RESET)] = Transition(Event.RESET, fail, first, tuple(spec.fail.guards.reset))
    table[(fail, Event.ACKNOWLEDGE)] = Transition(Event.ACKNOWLEDGE, fail, fail, ("fault_latched",))
    return table


class SafetyMachine:
    """The FSM of one session.

    Args:
        spec: a checked spec (:func:`~daror_runtime.fsm.spec.load_fsm_spec`).
        guards: name -> zero-argument predicate, for every guard the spec names (and ``fault_latched``).
        on_enter: called after every state change with the new state's spec (a :class:`StateSpec`,
            or the :class:`FailSpec`) and the outcome that caused it (also for a reset from the
            first state to itself, which re-enters it).
        on_acknowledge: called after an accepted acknowledge.

    Raises:
        ConfigurationError: a guard the spec names has no predicate.
    """

    def __init__(
        self,
        spec: FsmSpec,
        guards: Mapping[str, Callable[[], bool]],
        on_enter: Callable[[StateSpec | FailSpec, Outcome], None] | None = None,
        on_acknowledge: Callable[[Outcome], None] | None = None,
    ) -> None:
        self.spec = spec
        self.table = transition_table(spec)
        missing = sorted({g for t in self.table.values() for g in t.guards} - set(guards))
        if missing:
            raise ConfigurationError(f"no predicate for the guard(s) {', '.join(missing)}")
        self._guards = dict(guards)
        self._on_enter = on_enter
        self._on_acknowledge = on_acknowledge
        self._specs: dict[str, StateSpec | FailSpec] = {s.name: s for s in spec.states}
        self._specs[spec.fail.name] = spec.fail
        self._paths = {s.name: f"{s.superstate}.{s.name}" for s in spec.states}
        self._paths[spec.fail.name] = spec.fail.name
        self._names = {path: name for name, path in self._paths.items()}
        self._pending: Outcome | None = None
        self._model = _Model()
        children: dict[str, list[str]] = {}
        for s in spec.states:
            children.setdefault(s.superstate, []).append(s.name)
        states: list[object] = [{"name": name, "children": names} for name, names in children.items()]
        states.append(spec.fail.name)
        rows = []
        for t in self.table.values():
            row: dict[str, object] = {
                "trigger": t.event.value,
                "source": self._paths[t.source],
                "dest": None if t.internal else self._paths[t.dest],
                "conditions": [self._guards[g] for g in t.guards],
            }
            if t.internal:
                row["after"] = self._acknowledged
            rows.append(row)
        self._machine = _Machine(
            model=self._model,
            states=states,
            transitions=rows,
            initial=self._paths[spec.first.name],
            auto_transitions=False,
            ignore_invalid_triggers=False,
            queued=True,
            send_event=False,
            after_state_change=self._entered,
        )
        self._name = spec.first.name

    # --- state ----------------------------------------------------------------------------

    @property
    def state_name(self) -> str:
        """The current state's name (``FAIL`` for the fail state)."""
        return self._name

    @property
    def state(self) -> StateSpec | FailSpec:
        """The current state's spec."""
        return self._specs[self._name]

    @property
    def in_fail(self) -> bool:
        return self._name == self.spec.fail.name

    @property
    def library_state(self) -> str:
        """The state as ``transitions`` holds it (``superstate.state``); equal to :attr:`state_name` by path."""
        return self._model.state

    def _unmet_text(self, name: str) -> str:
        """``name (description: why, in figures)`` of a guard that does not hold."""
        if name not in GUARDS:
            return name
        why = getattr(self._guards[name], "why", None)
        detail = why() if why is not None else None
        return f"{name} ({GUARDS[name].description}" + (f": {detail})" if detail else ")")

    def unmet(self, event: Event) -> tuple[str, ...] | None:
        """Guards of ``event`` that do not hold now; None when there is no such transition."""
        transition = self.table.get((self._name, event))
        if transition is None:
            return None
        guards = self._guards
        return tuple(g for g in transition.guards if not guards[g]())

    # --- events ---------------------------------------------------------------------------

    def request(self, event: Event | str) -> Outcome:
        """Try ``event`` now; never raises for a refused or impossible event (the outcome says why)."""
        event = Event(event)
        source = self._name
        transition = self.table.get((source, event))
        if transition is None:
            return Outcome(event, False, source, None, (), self.why_not(event))
        guards = self._guards
        unmet = tuple(g for g in transition.guards if not guards[g]())
        if unmet:
            described = "; ".join(self._unmet_text(g) for g in unmet)
            return Outcome(event, False, source, None, unmet, f"unmet: {described}")
        outcome = Outcome(event, True, source, transition.dest, (), "")
        self._pending = outcome
        try:
            fired = getattr(self._model, event.value)()
        except MachineError as exc:  # our table and the library's disagree: a bug, never a silent pass
            raise ConfigurationError(f"the FSM library refused {event.value!r} from {source!r}: {exc}") from None
        finally:
            self._pending = None
        # A queued machine's trigger returns True even when its conditions refused, so compare the state.
        if not fired or self._names[self._model.state] != transition.dest:
            raise ConfigurationError(
                f"{event.value!r} from {source!r} did not reach {transition.dest!r}: its guards changed while it was "
                "decided (they cannot within one tick; a bug)"
            )
        return outcome

    def why_not(self, event: Event) -> str:
        """Why ``event`` has no transition from the current state (a sentence for the operator)."""
        state = self.state
        if not isinstance(state, StateSpec):  # FAIL
            return (
                f"in {state.name} only reset (once the fault is cleared and acknowledged) and acknowledge are possible"
            )
        if event == Event.ADVANCE:
            return f"{state.label} is the last state"
        if event == Event.REVERT:
            return f"{state.label} is the first state"
        if event == Event.FAIL:
            return f"{state.label} is an e-stop test state: a fault there is met by its reaction and recorded, it does not fail"
        return (
            f"nothing to acknowledge in {state.label}: faults are acknowledged in {self.spec.fail.name} or a test state"
        )

    # --- callbacks from transitions -------------------------------------------------------

    def _entered(self) -> None:
        self._name = self._names[self._model.state]
        outcome = self._pending
        if outcome is not None and self._on_enter is not None and outcome.event != Event.ACKNOWLEDGE:
            self._on_enter(self._specs[self._name], outcome)

    def _acknowledged(self) -> None:
        if self._on_acknowledge is not None and self._pending is not None:
            self._on_acknowledge(self._pending)
