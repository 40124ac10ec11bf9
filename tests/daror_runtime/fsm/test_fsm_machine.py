"""The safety machine against an oracle written here from the rules, for every state, event and guard outcome.

Rules (docs/fsm.md): advance goes to state number + 1 when every advance guard of the
state holds; revert to number - 1 with the state's revert guards (none from state 1); reset to the
first state from every state, FAIL included, with that state's reset guards; fail to FAIL only from
a state with fail_on_fault; acknowledge, guarded by fault_latched, only in FAIL and the test states,
without a state change. Every other (state, event) pair is refused with a reason.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import pytest

from daror_runtime.errors import ConfigurationError
from daror_runtime.fsm.guards import GUARDS
from daror_runtime.fsm.machine import Event, Outcome, SafetyMachine, transition_table
from daror_runtime.fsm.spec import FailSpec, FsmSpec, StateSpec, check_spec, load_fsm_spec

SHIPPED = load_fsm_spec()


def _state(
    number: int,
    name: str,
    superstate: str,
    mode: str,
    torque: float,
    fail_on_fault: bool,
    enforce_isb: bool = False,
    **guards: list[str],
) -> dict[str, Any]:
    return {
        "number": number,
        "name": name,
        "superstate": superstate,
        "mode": mode,
        "limits": {"torque_nm": torque, "velocity_rad_s": 1.0},
        "fail_on_fault": fail_on_fault,
        "enforce_isb": enforce_isb,
        "guards": guards,
    }


def _build(data: dict[str, Any]) -> FsmSpec:
    # The shipped reactions (they name no state, so they fit any spec); FAIL's reset needs the arm released.
    data = {
        **data,
        "fault_reactions": SHIPPED.model_dump()["fault_reactions"],
        "drive_reactions": SHIPPED.model_dump()["drive_reactions"],
    }
    data["fail"]["guards"]["reset"] = [*data["fail"]["guards"]["reset"], "arm_released"]
    spec = FsmSpec.model_validate(data)
    check_spec(spec, "synthetic")  # a valid spec, by the loader's own checks
    return spec


#: 4 states in 2 superstates; state 2 is a test state; revert and reset guards everywhere; FAIL renamed.
SYNTHETIC = _build(
    {
        "version": 1,
        "superstates": [{"name": "alpha"}, {"name": "beta"}],
        "states": [
            _state(1, "a_one", "alpha", "torque_off", 0.0, True, advance=["hal_connected"], reset=["faults_cleared"]),
            _state(
                2,
                "a_two",
                "alpha",
                "minimal_impedance",
                5.0,
                False,
                advance=["estop_tested", "estop_released"],
                revert=["robot_at_rest"],
                reset=["robot_at_rest", "fault_acknowledged"],
            ),
            _state(
                3,
                "b_one",
                "beta",
                "minimal_impedance",
                10.0,
                True,
                advance=[
                    "isb_limits_recorded",
                    "arm_inside_isb_limits",
                    "compensation_model_approved",
                    "no_active_faults",
                    "robot_at_rest",
                ],
                revert=["robot_at_rest", "no_active_faults"],
            ),
            _state(
                4,
                "b_two",
                "beta",
                "compensation",
                20.0,
                True,
                enforce_isb=True,
                revert=["robot_at_rest"],
                reset=["robot_at_rest", "no_active_faults", "faults_cleared"],
            ),
        ],
        "fail": {
            "name": "FAULT",
            "mode": "torque_off",
            "guards": {"reset": ["faults_cleared", "fault_acknowledged", "hal_connected"]},
        },
    }
)

#: The smallest spec: one state (first and last at once).
SINGLE = _build(
    {
        "version": 1,
        "superstates": [{"name": "only"}],
        "states": [_state(1, "solo", "only", "torque_off", 0.0, True)],
        "fail": {"guards": {"reset": ["faults_cleared", "fault_acknowledged"]}},
    }
)

SPECS = {"shipped": SHIPPED, "synthetic": SYNTHETIC, "single": SINGLE}


# --- the oracle ------------------------------------------------------------------------------


def oracle(spec: FsmSpec, source: str, event: Event) -> tuple[tuple[str, ...], str] | None:
    """(guards in spec order, destination) of ``event`` from ``source``, or None when it is refused outright."""
    by_number = {s.number: s for s in spec.states}
    first = by_number[1].name
    fail = spec.fail.name
    if source == fail:
        if event == Event.RESET:
            return tuple(spec.fail.guards.reset), first
        if event == Event.ACKNOWLEDGE:
            return ("fault_latched",), fail
        return None
    [state] = [s for s in spec.states if s.name == source]
    n = state.number
    if event == Event.ADVANCE:
        return (tuple(state.guards.advance), by_number[n + 1].name) if n + 1 in by_number else None
    if event == Event.REVERT:
        return (tuple(state.guards.revert), by_number[n - 1].name) if n > 1 else None
    if event == Event.RESET:
        return tuple(state.guards.reset), first
    if event == Event.FAIL:
        return ((), fail) if state.fail_on_fault else None
    return (("fault_latched",), source) if not state.fail_on_fault else None


def library_path(spec: FsmSpec, name: str) -> str:
    if name == spec.fail.name:
        return name
    [state] = [s for s in spec.states if s.name == name]
    return f"{state.superstate}.{name}"


def spec_of(spec: FsmSpec, name: str) -> StateSpec | FailSpec:
    return spec.fail if name == spec.fail.name else next(s for s in spec.states if s.name == name)


class Harness:
    """A fresh machine over ``spec`` whose guards read ``values`` (all true at first), recording callbacks."""

    def __init__(self, spec: FsmSpec) -> None:
        self.spec = spec
        self.values = dict.fromkeys(GUARDS, True)
        self.entered: list[tuple[StateSpec | FailSpec, Outcome]] = []
        self.acknowledged: list[Outcome] = []
        predicates: dict[str, Callable[[], bool]] = {g: (lambda g=g: self.values[g]) for g in GUARDS}
        self.machine = SafetyMachine(
            spec,
            predicates,
            on_enter=lambda state, outcome: self.entered.append((state, outcome)),
            on_acknowledge=self.acknowledged.append,
        )

    def go(self, event: Event) -> Outcome:
        outcome = self.machine.request(event)
        assert outcome.accepted, outcome
        return outcome

    def drive_to(self, target: str) -> Harness:
        """Advance (every guard true) to ``target``; FAIL by a fault in the first fail_on_fault state."""
        goal = target
        if target == self.spec.fail.name:
            goal = min((s for s in self.spec.states if s.fail_on_fault), key=lambda s: s.number).name
        while self.machine.state_name != goal:
            self.go(Event.ADVANCE)
        if target != goal:
            self.go(Event.FAIL)
        assert self.machine.state_name == target
        self.entered.clear()
        self.acknowledged.clear()
        return self


# --- the exhaustive check --------------------------------------------------------------------


def expected_case_count(spec: FsmSpec) -> int:
    """2^k per transition with k guards; 2 runs (all guards true, all false) per impossible pair."""
    total = 0
    last = max(s.number for s in spec.states)
    for s in spec.states:
        total += 2 if s.number == last else 2 ** len(s.guards.advance)
        total += 2 if s.number == 1 else 2 ** len(s.guards.revert)
        total += 2 ** len(s.guards.reset)
        total += 1 if s.fail_on_fault else 2  # fail has no guard; refused in a test state
        total += 2  # acknowledge: fault_latched true/false, or refused (2 runs)
    return total + 2 ** len(spec.fail.guards.reset) + 2 + 3 * 2  # FAIL: reset, acknowledge, 3 refused


def run_exhaustive(spec: FsmSpec) -> tuple[int, int]:
    """Check every state x event x guard outcome; returns (cases checked, cases accepted)."""
    cases = accepted_cases = 0
    sources = [s.name for s in spec.states] + [spec.fail.name]
    for source, event in itertools.product(sources, Event):
        expected = oracle(spec, source, event)
        guards = tuple(dict.fromkeys(expected[0])) if expected is not None else ()
        combos = itertools.product((True, False), repeat=len(guards)) if expected is not None else [(), ()]
        for k, combo in enumerate(combos):
            h = Harness(spec).drive_to(source)
            before = h.machine.library_state
            if expected is None:
                h.values = dict.fromkeys(GUARDS, k == 0)  # refused even with every guard true
            else:
                h.values.update(zip(guards, combo, strict=True))
            where = f"{source} --{event.value}--> with {dict(zip(guards, combo, strict=True))}"
            unmet = () if expected is None else tuple(g for g in expected[0] if not h.values[g])
            assert h.machine.unmet(event) == (None if expected is None else unmet), where
            outcome = h.machine.request(event)
            cases += 1
            assert (outcome.event, outcome.source) == (event, source), where
            if expected is not None and not unmet:
                accepted_cases += 1
                dest = expected[1]
                assert outcome == Outcome(event, True, source, dest, (), ""), where
                assert h.machine.state_name == dest, where
                assert h.machine.in_fail == (dest == spec.fail.name), where
                assert h.machine.state is spec_of(spec, dest), where
                assert h.machine.library_state == library_path(spec, dest), where
                if dest == spec.fail.name:
                    assert h.machine.library_state == dest, where
                else:
                    assert h.machine.library_state.endswith("." + dest), where
                if event == Event.ACKNOWLEDGE:
                    assert h.entered == [], where
                    assert h.acknowledged == [outcome], where
                else:
                    assert h.entered == [(spec_of(spec, dest), outcome)], where
                    assert h.acknowledged == [], where
            else:
                assert not outcome.accepted, where
                assert outcome.dest is None, where
                assert outcome.unmet == unmet, where
                assert outcome.reason, where
                if unmet:
                    assert outcome.reason.startswith("unmet: "), where
                    assert all(f"{g} ({GUARDS[g].description})" in outcome.reason for g in unmet), where
                assert h.machine.state_name == source, where
                assert h.machine.library_state == before == library_path(spec, source), where
                assert (h.entered, h.acknowledged) == ([], []), where
    return cases, accepted_cases


# FAIL's reset carries arm_released too: 8 more combinations in synthetic (3 -> 4 guards), 4 more in single (2 -> 3).
@pytest.mark.parametrize(("name", "count"), [("shipped", None), ("synthetic", 102), ("single", 24)])
def test_exhaustive(name: str, count: int | None) -> None:
    spec = SPECS[name]
    cases, accepted = run_exhaustive(spec)
    assert cases == expected_case_count(spec)
    if count is not None:  # the synthetic specs are fixed here: their counts are worked out by hand
        assert cases == count
    pairs = (len(spec.states) + 1) * len(Event)
    possible = sum(
        oracle(spec, s, e) is not None for s in [*(x.name for x in spec.states), spec.fail.name] for e in Event
    )
    assert accepted == possible == len(transition_table(spec))  # one all-true combination per transition
    assert pairs - possible == {"shipped": 15, "synthetic": 9, "single": 6}[name]


def test_exhaustive_count_of_the_shipped_spec() -> None:
    # 10 states + FAIL, test states 2, 5, 7: 129 guard combinations over 40 transitions (rom_limits' advance: 4
    # guards, 16 combinations; settings' advance and FAIL's reset: 3 guards, 8 combinations) + 15 refused pairs x 2.
    assert expected_case_count(SHIPPED) == 159


# --- callbacks -------------------------------------------------------------------------------


def test_on_enter_once_per_state_change() -> None:
    h = Harness(SHIPPED)
    outcomes = [h.go(Event.ADVANCE) for _ in SHIPPED.states[1:]]
    outcomes.append(h.go(Event.REVERT))
    outcomes.append(h.go(Event.FAIL))
    ack = h.go(Event.ACKNOWLEDGE)
    outcomes.append(h.go(Event.RESET))
    names = [s.name for s in SHIPPED.states]
    assert [state.name for state, _ in h.entered] == [*names[1:], names[-2], "FAIL", names[0]]
    assert [outcome for _, outcome in h.entered] == outcomes
    assert all(state.name == outcome.dest for state, outcome in h.entered)
    assert h.acknowledged == [ack]
    assert ack.dest == ack.source == "FAIL"
    assert h.machine.state_name == "startup"
    assert h.machine.library_state == "pre_op.startup"


def test_reset_from_first_state_reenters_it() -> None:
    for spec in SPECS.values():
        h = Harness(spec)
        outcome = h.go(Event.RESET)
        assert outcome.source == outcome.dest == spec.first.name
        assert h.entered == [(spec.first, outcome)]
        assert h.machine.state_name == spec.first.name


@pytest.mark.parametrize("where", ["safety_check", "safety_experience", "operative_check", "FAIL"])
def test_acknowledge_calls_on_acknowledge_only(where: str) -> None:
    h = Harness(SHIPPED).drive_to(where)
    before = h.machine.library_state
    outcome = h.go(Event.ACKNOWLEDGE)
    assert outcome == Outcome(Event.ACKNOWLEDGE, True, where, where, (), "")
    assert h.entered == []
    assert h.acknowledged == [outcome]
    assert h.machine.state_name == where
    assert h.machine.library_state == before
    h.values["fault_latched"] = False
    refused = h.machine.request(Event.ACKNOWLEDGE)
    assert (refused.accepted, refused.unmet) == (False, ("fault_latched",))
    assert h.acknowledged == [outcome]


def test_machine_without_callbacks() -> None:
    machine = SafetyMachine(SHIPPED, dict.fromkeys(GUARDS, lambda: True))
    assert machine.request("advance").dest == "safety_check"
    assert machine.request("acknowledge").accepted
    assert machine.request(Event.RESET).dest == "startup"
    assert machine.request("fail").dest == "FAIL"
    assert machine.in_fail
    assert machine.library_state == "FAIL"


# --- refusals --------------------------------------------------------------------------------


def test_refused_advance_names_every_unmet_guard() -> None:
    checked = 0
    for state in SHIPPED.states:
        if not state.guards.advance:
            continue
        h = Harness(SHIPPED).drive_to(state.name)
        h.values = dict.fromkeys(GUARDS, False)
        outcome = h.machine.request(Event.ADVANCE)
        assert not outcome.accepted
        assert outcome.dest is None
        assert outcome.unmet == tuple(state.guards.advance)
        assert outcome.reason == "unmet: " + "; ".join(f"{g} ({GUARDS[g].description})" for g in state.guards.advance)
        for g in state.guards.advance:  # one missing guard: only that one is named
            h.values = dict.fromkeys(GUARDS, True)
            h.values[g] = False
            single = h.machine.request(Event.ADVANCE)
            assert single.unmet == (g,)
            assert single.reason == f"unmet: {g} ({GUARDS[g].description})"
        assert h.machine.state_name == state.name
        checked += 1
    assert checked == len(SHIPPED.states) - 1


@pytest.mark.parametrize(
    ("where", "event", "fragment"),
    [
        ("compensation", Event.ADVANCE, "10 compensation is the last state"),
        ("startup", Event.REVERT, "1 startup is the first state"),
        ("safety_check", Event.FAIL, "2 safety_check is an e-stop test state"),
        ("settings", Event.ACKNOWLEDGE, "nothing to acknowledge in 3 settings"),
        ("FAIL", Event.ADVANCE, "in FAIL only reset"),
        ("FAIL", Event.FAIL, "in FAIL only reset"),
    ],
)
def test_refusal_reasons(where: str, event: Event, fragment: str) -> None:
    h = Harness(SHIPPED).drive_to(where)
    outcome = h.machine.request(event)
    assert outcome == Outcome(event, False, where, None, (), outcome.reason)
    assert fragment in outcome.reason


def test_missing_guard_predicate_is_refused() -> None:
    needed = {g for t in transition_table(SHIPPED).values() for g in t.guards}
    named = {g for s in SHIPPED.states for k in ("advance", "revert", "reset") for g in getattr(s.guards, k)}
    assert needed == named | set(SHIPPED.fail.guards.reset) | {"fault_latched"}
    for missing in sorted(needed):
        predicates = {g: (lambda: True) for g in needed if g != missing}
        with pytest.raises(ConfigurationError, match=f"no predicate for the guard\\(s\\) {missing}$"):
            SafetyMachine(SHIPPED, predicates)
    with pytest.raises(ConfigurationError) as info:
        SafetyMachine(SHIPPED, {})
    assert str(info.value) == f"no predicate for the guard(s) {', '.join(sorted(needed))}"
    SafetyMachine(SHIPPED, {g: (lambda: True) for g in needed})  # exactly the needed ones suffice


def test_guard_changing_between_check_and_fire_is_not_reported_as_accepted() -> None:
    calls = 0

    def flaky() -> bool:  # true when request checks it, false when the library checks it
        nonlocal calls
        calls += 1
        return calls == 1

    predicates = dict.fromkeys(GUARDS, lambda: True) | {"hal_connected": flaky}
    machine = SafetyMachine(SHIPPED, predicates)
    try:
        outcome = machine.request(Event.ADVANCE)
    except ConfigurationError:
        return  # the documented behaviour
    assert outcome.dest == machine.state_name, f"{outcome} but the machine is in {machine.state_name}"


# --- the transition table --------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SPECS))
def test_transition_table(name: str) -> None:
    spec = SPECS[name]
    table = transition_table(spec)
    states = spec.states
    fail = spec.fail.name
    first, last = states[0].name, states[-1].name

    def sources(event: Event) -> set[str]:
        return {source for source, e in table if e == event}

    assert sources(Event.ADVANCE) == {s.name for s in states} - {last}
    assert sources(Event.REVERT) == {s.name for s in states} - {first}
    assert sources(Event.RESET) == {s.name for s in states} | {fail}
    assert sources(Event.FAIL) == {s.name for s in states if s.fail_on_fault}
    assert sources(Event.ACKNOWLEDGE) == {s.name for s in states if not s.fail_on_fault} | {fail}
    for (source, event), t in table.items():
        assert (t.source, t.event) == (source, event)
        assert oracle(spec, source, event) == (t.guards, t.dest)
        assert t.internal == (event == Event.ACKNOWLEDGE)
    # (n - 1) advances + (n - 1) reverts + n resets + one fail or acknowledge per state + FAIL's reset and acknowledge
    assert len(table) == 4 * len(states)


def test_shipped_table_fail_and_acknowledge_sources() -> None:
    table = transition_table(SHIPPED)
    assert sorted(n for n, s in enumerate(SHIPPED.states, 1) if (s.name, Event.FAIL) in table) == [1, 3, 4, 6, 8, 9, 10]
    assert sorted(n for n, s in enumerate(SHIPPED.states, 1) if (s.name, Event.ACKNOWLEDGE) in table) == [2, 5, 7]
    assert table[("FAIL", Event.RESET)].guards == ("faults_cleared", "fault_acknowledged", "arm_released")
    assert table[("FAIL", Event.ACKNOWLEDGE)].guards == ("fault_latched",)
