"""``fsm_spec.yaml``: the shipped spec, its JSON Schema, every way a spec can be wrong, and the CLI.

The malformed specs are made by editing the text of the shipped spec (so the line numbers are
those a person editing the file would see) and the expected line of every problem is computed
from the text that was written, never hard-coded.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import pytest
import yaml

from daror_runtime.cli import main
from daror_runtime.fsm.diagram import mermaid
from daror_runtime.fsm.guards import GUARDS
from daror_runtime.fsm.modes import MODES
from daror_runtime.fsm.spec import (
    DEFAULT_SPEC_PATH,
    INVARIANTS,
    SCHEMA_PATH,
    FsmSpec,
    FsmSpecError,
    load_fsm_spec,
    spec_json_schema_text,
)
from daror_runtime.safety.faults import FaultKind
from hal.robot import load_description

SHIPPED_TEXT = DEFAULT_SPEC_PATH.read_text(encoding="utf-8")
SHIPPED_DATA = yaml.safe_load(SHIPPED_TEXT)
#: Index in ``states`` of every shipped state, by name (read with PyYAML, not with the code under test).
IDX = {state["name"]: i for i, state in enumerate(SHIPPED_DATA["states"])}


# --- editing the shipped text ----------------------------------------------------------------

Where = int | str | None  # a state's index, a top-level section ("fail", "fault_reactions"), or None for the whole text


def _span(text: str, where: Where) -> tuple[int, int]:
    """Start and end offsets of a state's block (by index), of the fail section, or of the whole text."""
    if where is None:
        return 0, len(text)
    if isinstance(where, str):  # a top-level section: fail, fault_reactions, drive_reactions
        start = text.index(f"\n{where}:") + 1
    else:
        assert isinstance(where, int)
        starts = [m.start() + 1 for m in re.finditer(r"\n  - number:", text)]
        start = starts[where]
        following = [s for s in starts if s > start]
        if following:
            return start, following[0]
    top_level = re.compile(r"\n(?=\S)")  # the next top-level key ends a block
    match = top_level.search(text, start)
    return start, match.start() + 1 if match else len(text)


def edit(text: str, where: Where, old: str, new: str) -> str:
    """``text`` with the one occurrence of ``old`` inside ``where`` replaced by ``new``."""
    start, end = _span(text, where)
    block = text[start:end]
    assert block.count(old) == 1, f"{old!r} must occur once in {where!r} of the shipped spec:\n{block}"
    return text[:start] + block.replace(old, new) + text[end:]


def _block(text: str, where: Where) -> str:
    start, end = _span(text, where)
    return text[start:end]


def line(text: str, needle: str, where: Where = None) -> int:
    """1-based line of the one occurrence of ``needle`` inside ``where`` of ``text``."""
    start, end = _span(text, where)
    block = text[start:end]
    assert block.count(needle) == 1, f"{needle!r} must occur once in {where!r}:\n{block}"
    return text.count("\n", 0, start + block.index(needle)) + 1


def state_line(text: str, index: int) -> int:
    """The line a state's mapping starts on (``  - number: N``)."""
    return text.count("\n", 0, _span(text, index)[0]) + 1


def first_key_line(text: str) -> int:
    """The line of the first key of the top-level mapping (after the header comments)."""
    for number, content in enumerate(text.splitlines(), start=1):
        if content.strip() and not content.lstrip().startswith("#"):
            return number
    raise AssertionError("no content")


class Expect(NamedTuple):
    line: int
    field: str
    fragment: str  # part of the message
    invariant: str | None = None  # the safety invariant the message must name


DEVICE = load_description()


Case = Callable[[str], tuple[str, list[Expect]]]
CASES: dict[str, Case] = {}


def case(name: str) -> Callable[[Case], Case]:
    def register(function: Case) -> Case:
        CASES[name] = function
        return function

    return register


def assert_problems(path: Path, expected: list[Expect]) -> str:
    """``load_fsm_spec(path)`` raises, with exactly one line per expected problem, each as expected."""
    with pytest.raises(FsmSpecError) as info:
        load_fsm_spec(path)
    message = str(info.value)
    lines = message.splitlines()
    assert len(lines) == len(expected), f"expected {len(expected)} problem(s), got:\n{message}"
    for want in expected:
        prefix = f"{path}: line {want.line}, field {want.field}: "
        hits = [x for x in lines if x.startswith(prefix)]
        assert hits, f"no problem starts with {prefix!r}:\n{message}"
        matching = [x for x in hits if want.fragment in x]
        assert matching, f"{want.fragment!r} not in {hits}"
        if want.invariant is not None:
            assert want.invariant in INVARIANTS, want.invariant
            tag = f"[safety invariant: {want.invariant}]"
            assert any(x.endswith(tag) for x in matching), f"{tag!r} not named in {matching}"
    return message


# --- the malformed specs ---------------------------------------------------------------------


@case("unknown guard")
def _unknown_guard(text: str) -> tuple[str, list[Expect]]:
    i = IDX["startup"]
    bad = edit(text, i, "advance: [hal_connected,", "advance: [hal_conected,")
    return bad, [Expect(line(bad, "hal_conected"), f"states.{i}.guards.advance.0", "unknown guard 'hal_conected'")]


@case("unknown guard in FAIL's reset")
def _unknown_fail_guard(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fail", "arm_released]", "arm_released, reboot]")
    return bad, [Expect(line(bad, "reboot"), "fail.guards.reset.3", "unknown guard 'reboot'")]


@case("guard listed twice")
def _guard_twice(text: str) -> tuple[str, list[Expect]]:
    i = IDX["settings"]
    bad = edit(
        text,
        i,
        "advance: [settings_confirmed, pilot_named, no_active_faults]",
        "advance: [settings_confirmed, pilot_named, no_active_faults, settings_confirmed]",
    )
    return bad, [
        Expect(line(bad, "advance:", i), f"states.{i}.guards.advance.3", "guard 'settings_confirmed' is listed twice")
    ]


@case("unknown mode")
def _unknown_mode(text: str) -> tuple[str, list[Expect]]:
    i = IDX["training"]
    bad = edit(text, i, "mode: hold", "mode: hover")
    return bad, [Expect(line(bad, "mode: hover"), f"states.{i}.mode", "unknown mode 'hover'; expected one of")]


@case("duplicate state name")
def _duplicate_name(text: str) -> tuple[str, list[Expect]]:
    i, first = IDX["training"], IDX["identification"]
    bad = edit(text, i, "name: training", "name: identification")
    return bad, [
        Expect(
            line(bad, "name: identification", i),
            f"states.{i}.name",
            f"state name 'identification' is used twice (also states.{first})",
        )
    ]


@case("duplicate state number")
def _duplicate_number(text: str) -> tuple[str, list[Expect]]:
    i = IDX["training"]
    n = SHIPPED_DATA["states"][i]["number"]
    bad = edit(text, i, f"number: {n}\n", f"number: {n - 1}\n")
    return bad, [
        Expect(
            line(bad, "number:", i), f"states.{i}.number", f"state number {n - 1} is used twice (also states.{i - 1})"
        )
    ]


@case("missing fail section")
def _missing_fail(text: str) -> tuple[str, list[Expect]]:
    start, end = _span(text, "fail")
    bad = text[:start] + text[end:]
    return bad, [Expect(first_key_line(bad), "fail", "Field required")]


@case("gap in the numbering")
def _gap(text: str) -> tuple[str, list[Expect]]:
    i = len(SHIPPED_DATA["states"]) - 1
    name, n = SHIPPED_DATA["states"][i]["name"], SHIPPED_DATA["states"][i]["number"]
    bad = edit(text, i, f"number: {n}\n", f"number: {n + 1}\n")
    return bad, [
        Expect(
            line(bad, "number:", i),
            f"states.{i}.number",
            f"state {n + 1} {name} is unreachable by advance: no state is numbered {n}",
        )
    ]


@case("states listed out of order")
def _out_of_order(text: str) -> tuple[str, list[Expect]]:
    a, b = IDX["safety_check"], IDX["settings"]  # consecutive, same superstate: only the order is wrong
    (sa, ea), (sb, eb) = _span(text, a), _span(text, b)
    assert ea == sb
    bad = text[:sa] + text[sb:eb] + text[sa:ea] + text[eb:]
    return bad, [
        Expect(
            state_line(bad, a),
            f"states.{a}.number",
            f"state {b + 1} settings is listed as state {a + 1}; list the states in advance order 1..N",
        ),
        Expect(state_line(bad, b), f"states.{b}.number", f"state {a + 1} safety_check is listed as state {b + 1}"),
    ]


@case("test state in torque_off")
def _test_state_torque_off(text: str) -> tuple[str, list[Expect]]:
    i = IDX["safety_check"]
    bad = edit(text, i, "mode: minimal_impedance", "mode: torque_off")
    bad = edit(bad, i, "torque_nm: 5.0", "torque_nm: 0.0")  # a consistent limit: only the test state is wrong
    return bad, [
        Expect(
            line(bad, "fail_on_fault: false", i),
            f"states.{i}.fail_on_fault",
            "its mode 'torque_off' applies no torque for the e-stop to remove",
            "test states are pilot-driven",
        )
    ]


@case("test state in identification")
def _test_state_identification(text: str) -> tuple[str, list[Expect]]:
    i = IDX["operative_check"]  # enforces the ISB limits already, so identification is otherwise fine
    bad = edit(text, i, "mode: compensation", "mode: identification")
    return bad, [
        Expect(
            line(bad, "fail_on_fault: false", i),
            f"states.{i}.fail_on_fault",
            "its mode 'identification' moves the robot on its own",
            "test states are pilot-driven",
        )
    ]


@case("test state without an e-stop guard")
def _test_state_no_estop(text: str) -> tuple[str, list[Expect]]:
    i = IDX["safety_check"]
    bad = edit(text, i, "advance: [estop_operator_tested, estop_pilot_tested, ", "advance: [")
    return bad, [
        Expect(
            line(bad, "advance:", i),
            f"states.{i}.guards.advance",
            "so it must be an e-stop test: its advance guards need one of",
            "test states test an e-stop",
        )
    ]


@case("e-stop test guard in a fail_on_fault state")
def _estop_guard_in_fail_state(text: str) -> tuple[str, list[Expect]]:
    i = IDX["pilot_installation"]
    bad = edit(text, i, "advance: [installation_confirmed,", "advance: [installation_confirmed, estop_tested,")
    return bad, [
        Expect(
            line(bad, "fail_on_fault: true", i),
            f"states.{i}.fail_on_fault",
            "guard 'estop_tested' could never hold",
            "test states test an e-stop",
        )
    ]


@case("test state made fail_on_fault")
def _test_state_made_failing(text: str) -> tuple[str, list[Expect]]:
    i = IDX["safety_check"]
    bad = edit(text, i, "fail_on_fault: false", "fail_on_fault: true")
    # safety_check is no e-stop test any more: the first one is safety_experience, after two states with torque
    first_test = IDX["safety_experience"]
    before = [k for k in range(first_test) if SHIPPED_DATA["states"][k]["mode"] != "torque_off"]
    assert before == [i, IDX["pilot_installation"]]
    return bad, [
        Expect(
            line(bad, "fail_on_fault: true", i),
            f"states.{i}.fail_on_fault",
            "guard 'estop_operator_tested' could never hold",
            "test states test an e-stop",
        ),
        *(
            Expect(
                line(bad, "mode:", k),
                f"states.{k}.mode",
                f"comes before the first e-stop test state, {first_test + 1} safety_experience",
                "e-stops tested before torque",
            )
            for k in before
        ),
    ]


@case("FAIL reset without fault_acknowledged")
def _fail_reset_no_ack(text: str) -> tuple[str, list[Expect]]:
    bad = edit(
        text,
        "fail",
        "reset: [faults_cleared, fault_acknowledged, arm_released]",
        "reset: [faults_cleared, arm_released]",
    )
    return bad, [
        Expect(
            line(bad, "reset:", "fail"),
            "fail.guards.reset",
            "cleared and acknowledged: add fault_acknowledged",
            "FAIL left only when cleared and acknowledged",
        )
    ]


@case("FAIL reset with no guard")
def _fail_reset_empty(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fail", "reset: [faults_cleared, fault_acknowledged, arm_released]", "reset: []")
    return bad, [
        Expect(line(bad, "reset:", "fail"), "fail.guards.reset", "add faults_cleared, fault_acknowledged"),
        Expect(
            line(bad, "reset:", "fail"), "fail.guards.reset", "add arm_released", "FAIL left only with the arm released"
        ),
    ]


# --- the fault reactions -------------------------------------------------------------------------------


def reaction_line(text: str, kind: str) -> int:
    """The line of ``kind``'s entry in ``fault_reactions`` (a flow mapping on one line)."""
    return line(text, f"  {kind}: {{", "fault_reactions")


@case("a fault kind without a reaction")
def _reaction_missing(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fault_reactions", "  overrun: {reaction: lower}\n", "")
    return bad, [
        Expect(
            reaction_line(bad, "estop"),
            "fault_reactions",
            "no reaction for the fault kind(s) overrun",
            "every fault has a reaction",
        )
    ]


@case("a state override naming no state")
def _reaction_unknown_state(text: str) -> tuple[str, list[Expect]]:
    bad = edit(
        text,
        "fault_reactions",
        "velocity: {reaction: lower}",
        "velocity: {reaction: lower, states: {compensaton: hold}}",
    )
    return bad, [
        Expect(
            reaction_line(bad, "velocity"),
            "fault_reactions.velocity.states.compensaton",
            "no state is called 'compensaton'",
            "every fault has a reaction",
        )
    ]


@case("a drive fault keeps its joint's torque")
def _reaction_untrusted_joint(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fault_reactions", 'drive: {reaction: lower, faulted_joint: "off"}', "drive: {reaction: lower}")
    return bad, [
        Expect(
            reaction_line(bad, "drive"),
            "fault_reactions.drive.faulted_joint",
            "expected faulted_joint: off",
            "untrusted joints get no torque",
        )
    ]


@case("a sensor fault keeps its joint's torque")
def _reaction_untrusted_sensor(text: str) -> tuple[str, list[Expect]]:
    old = 'jump: {reaction: lower, faulted_joint: "off"}'
    bad = edit(text, "fault_reactions", old, "jump: {reaction: hold, faulted_joint: with_the_arm}")
    return bad, [
        Expect(
            reaction_line(bad, "jump"),
            "fault_reactions.jump.faulted_joint",
            "a jump fault means its joint's drive, torque path or sensors cannot be trusted",
            "untrusted joints get no torque",
        )
    ]


@case("stale data lowers the arm")
def _reaction_blind(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fault_reactions", 'stale: {reaction: "off"}', "stale: {reaction: lower}")
    return bad, [
        Expect(
            reaction_line(bad, "stale"),
            "fault_reactions.stale.reaction",
            "nothing can lower the arm without them; expected off",
            "no reaction without fresh readings",
        )
    ]


@case("stale data holds the arm in one state")
def _reaction_blind_in_state(text: str) -> tuple[str, list[Expect]]:
    bad = edit(
        text, "fault_reactions", 'stale: {reaction: "off"}', 'stale: {reaction: "off", states: {training: hold}}'
    )
    return bad, [
        Expect(
            reaction_line(bad, "stale"),
            "fault_reactions.stale.states.training",
            "(in state training): nothing can hold the arm",
            "no reaction without fresh readings",
        )
    ]


@case("an e-stop holds the arm")
def _reaction_estop_hold(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fault_reactions", 'estop: {reaction: "off"}', "estop: {reaction: hold}")
    return bad, [
        Expect(
            reaction_line(bad, "estop"),
            "fault_reactions.estop.reaction",
            "expected off or lower (with within_s), not hold",
            "e-stops stop in category 0 or 1",
        )
    ]


@case("an e-stop lowers without a bound on a robot wired to safe torque off")
def _reaction_estop_lower(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fault_reactions", 'estop: {reaction: "off"}', "estop: {reaction: lower}")
    return bad, [
        Expect(
            reaction_line(bad, "estop"),
            "fault_reactions.estop.within_s",
            "needs within_s",
            "e-stops stop in category 0 or 1",
        ),
        Expect(
            reaction_line(bad, "estop"),
            "fault_reactions.estop.reaction",
            "wired to the drives' safe torque off",
            "e-stops stop in category 0 or 1",
        ),
    ]


@case("an e-stop lowers on a robot wired to safe torque off")
def _reaction_estop_sto(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fault_reactions", 'estop: {reaction: "off"}', "estop: {reaction: lower, within_s: 8.0}")
    return bad, [
        Expect(
            reaction_line(bad, "estop"),
            "fault_reactions.estop.reaction",
            "the runtime cannot lower the arm; expected off",
            "e-stops stop in category 0 or 1",
        )
    ]


@case("a software fault holds with the model")
def _reaction_suspect_model(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fault_reactions", "software: {reaction: lower, support: a_priori}", "software: {reaction: lower}")
    return bad, [
        Expect(
            reaction_line(bad, "software"),
            "fault_reactions.software.support",
            "may come from the compensation model: expected support: a_priori",
            "no reaction leans on a suspect model",
        )
    ]


@case("a reaction holds in a torque-free state")
def _reaction_torque_free(text: str) -> tuple[str, list[Expect]]:
    bad = edit(
        text,
        "fault_reactions",
        "isb_limit: {reaction: lower}",
        "isb_limit: {reaction: lower, states: {settings: hold}}",
    )
    return bad, [
        Expect(
            reaction_line(bad, "isb_limit"),
            "fault_reactions.isb_limit.states.settings",
            "mode 'torque_off' applies no torque, so the robot holds nothing there to hold",
            "reactions hold only what the robot held",
        )
    ]


@case("a bare off in a reaction")
def _reaction_bare_off(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fault_reactions", 'estop: {reaction: "off"}', "estop: {reaction: off}")
    return bad, [Expect(reaction_line(bad, "estop"), "fault_reactions.estop.reaction", 'write "off" in quotes')]


@case("within_s on another fault kind")
def _reaction_within_elsewhere(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fault_reactions", "velocity: {reaction: lower}", "velocity: {reaction: lower, within_s: 4}")
    return bad, [Expect(reaction_line(bad, "velocity"), "fault_reactions.velocity.within_s", "e-stop's reaction only")]


@case("an unknown fault kind")
def _reaction_unknown_kind(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fault_reactions", "  overrun: {reaction: lower}", "  overrunn: {reaction: lower}")
    return bad, [Expect(reaction_line(bad, "overrunn"), "fault_reactions.overrunn", "overrun")]


@case("a drive ramp without its duration")
def _drive_ramp_without_duration(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "drive_reactions", "master_lost: {reaction: ramp, ramp_s: 3.0}", "master_lost: {reaction: ramp}")
    return bad, [
        Expect(line(bad, "master_lost:", "drive_reactions"), "drive_reactions.master_lost.ramp_s", "ramp needs ramp_s")
    ]


@case("a drive ramp longer than the bound")
def _drive_ramp_too_long(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "drive_reactions", "ramp_s: 3.0", "ramp_s: 60.0")
    return bad, [
        Expect(
            line(bad, "master_lost:", "drive_reactions"),
            "drive_reactions.master_lost.ramp_s",
            "less than or equal to 10",
        )
    ]


@case("FAIL mode applies torque")
def _fail_mode_torque(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fail", "mode: torque_off", "mode: minimal_impedance")
    return bad, [
        Expect(
            line(bad, "mode:", "fail"),
            "fail.mode",
            "the FAIL state must remove torque; mode 'minimal_impedance' applies torque",
            "FAIL removes torque",
        )
    ]


@case("torque_nm not a number")
def _torque_lots(text: str) -> tuple[str, list[Expect]]:
    i = IDX["pilot_installation"]
    bad = edit(text, i, "torque_nm: 10.0", 'torque_nm: "lots"')
    return bad, [Expect(line(bad, '"lots"'), f"states.{i}.limits.torque_nm", "Input should be a valid number")]


@case("fail_on_fault not a boolean")
def _fail_on_fault_maybe(text: str) -> tuple[str, list[Expect]]:
    i = IDX["settings"]
    bad = edit(text, i, "fail_on_fault: true", "fail_on_fault: maybe")
    return bad, [Expect(line(bad, "maybe"), f"states.{i}.fail_on_fault", "Input should be a valid boolean")]


@case("number not an integer")
def _number_fraction(text: str) -> tuple[str, list[Expect]]:
    i = IDX["rom_limits"]
    n = SHIPPED_DATA["states"][i]["number"]
    bad = edit(text, i, f"number: {n}\n", f"number: {n}.5\n")
    return bad, [Expect(line(bad, f"number: {n}.5"), f"states.{i}.number", "Input should be a valid integer")]


@case("velocity limit 0")
def _velocity_zero(text: str) -> tuple[str, list[Expect]]:
    i = IDX["startup"]
    bad = edit(text, i, "velocity_rad_s: 2.0", "velocity_rad_s: 0")
    return bad, [Expect(line(bad, "velocity_rad_s: 0"), f"states.{i}.limits.velocity_rad_s", "greater than 0")]


@case("unknown version")
def _version(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, None, "\nversion: 1\n", "\nversion: 2\n")
    return bad, [Expect(line(bad, "version: 2"), "version", "Input should be 1")]


@case("misspelt field")
def _typo(text: str) -> tuple[str, list[Expect]]:
    i = IDX["startup"]
    bad = edit(text, i, "fail_on_fault: true", "fail_on_falt: true")
    return bad, [
        Expect(line(bad, "fail_on_falt"), f"states.{i}.fail_on_falt", "Extra inputs are not permitted"),
        Expect(state_line(bad, i), f"states.{i}.fail_on_fault", "Field required"),  # the state's own line
    ]


@case("undeclared superstate")
def _undeclared_superstate(text: str) -> tuple[str, list[Expect]]:
    i = IDX["startup"]
    bad = edit(text, i, "superstate: pre_op", "superstate: preop")
    declared = ", ".join(s["name"] for s in SHIPPED_DATA["superstates"])
    return bad, [
        Expect(
            line(bad, "preop"), f"states.{i}.superstate", f"superstate 'preop' is not declared (declared: {declared})"
        )
    ]


@case("superstate not consecutive")
def _superstate_split(text: str) -> tuple[str, list[Expect]]:
    i = IDX["rom_limits"]  # installation -> pre_op, after pilot_installation and safety_experience
    bad = edit(text, i, "superstate: installation", "superstate: pre_op")
    return bad, [
        Expect(
            line(bad, "superstate:", i),
            f"states.{i}.superstate",
            f"state {i + 1} rom_limits returns to superstate 'pre_op'; a superstate's states must be consecutive",
        )
    ]


@case("superstate without a state")
def _empty_superstate(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, None, "\nstates:\n", "\n  - name: spare\n\nstates:\n")
    k = len(SHIPPED_DATA["superstates"])
    return bad, [Expect(line(bad, "- name: spare"), f"superstates.{k}.name", "superstate 'spare' has no state")]


@case("torque limit on a torque_off state")
def _torque_off_with_limit(text: str) -> tuple[str, list[Expect]]:
    i = IDX["startup"]
    bad = edit(text, i, "torque_nm: 0.0", "torque_nm: 1.5")
    return bad, [
        Expect(
            line(bad, "torque_nm: 1.5"),
            f"states.{i}.limits.torque_nm",
            "mode 'torque_off' applies no torque; its torque limit must be 0, not 1.5",
            "torque limit fits the mode",
        )
    ]


@case("zero torque limit on a torque mode")
def _torque_mode_zero(text: str) -> tuple[str, list[Expect]]:
    i = IDX["pilot_installation"]
    bad = edit(text, i, "torque_nm: 10.0", "torque_nm: 0.0")
    return bad, [
        Expect(
            line(bad, "torque_nm:", i),
            f"states.{i}.limits.torque_nm",
            "mode 'minimal_impedance' applies torque but the torque limit is 0",
            "torque limit fits the mode",
        )
    ]


@case("revert guards on the first state")
def _revert_first(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, 0, "      advance: [", "      revert: [estop_released]\n      advance: [")
    return bad, [Expect(line(bad, "revert:", 0), "states.0.guards.revert", "is the first state: it has no revert")]


@case("advance guards on the last state")
def _advance_last(text: str) -> tuple[str, list[Expect]]:
    i = len(SHIPPED_DATA["states"]) - 1
    bad = edit(
        text, i, "    enforce_isb: true\n", "    enforce_isb: true\n    guards:\n      advance: [no_active_faults]\n"
    )
    return bad, [Expect(line(bad, "advance:", i), f"states.{i}.guards.advance", "is the last state: it has no advance")]


@case("enforce_isb before the ISB limits are recorded")
def _isb_too_early(text: str) -> tuple[str, list[Expect]]:
    i = IDX["pilot_installation"]
    bad = edit(text, i, "    fail_on_fault: true\n", "    fail_on_fault: true\n    enforce_isb: true\n")
    return bad, [
        Expect(
            line(bad, "enforce_isb:", i),
            f"states.{i}.enforce_isb",
            "enforces the ISB limits but no earlier state's advance requires isb_limits_recorded",
            "ISB limits recorded before enforced",
        )
    ]


@case("identification without enforce_isb")
def _identification_no_isb(text: str) -> tuple[str, list[Expect]]:
    i = IDX["identification"]
    bad = edit(text, i, "enforce_isb: true", "enforce_isb: false")
    return bad, [
        Expect(
            line(bad, "enforce_isb: false"),
            f"states.{i}.enforce_isb",
            "must run inside the pilot's ISB limits (enforce_isb: true)",
            "position control inside the ISB limits",
        )
    ]


@case("identification with enforce_isb left out")
def _identification_isb_missing(text: str) -> tuple[str, list[Expect]]:
    i = IDX["identification"]
    bad = edit(text, i, "    enforce_isb: true\n", "")
    return bad, [Expect(state_line(bad, i), f"states.{i}.enforce_isb", "must run inside the pilot's ISB limits")]


@case("FAIL named like a state")
def _fail_name_clash(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, "fail", "name: FAIL", "name: training")
    i = IDX["training"]
    return bad, [
        Expect(line(bad, "name: training", i), f"states.{i}.name", "state name 'training' is the FAIL state's name")
    ]


@case("several problems at once")
def _several(text: str) -> tuple[str, list[Expect]]:
    a, b, c, d = IDX["startup"], IDX["settings"], IDX["training"], IDX["rom_limits"]
    bad = edit(text, a, "hal_connected", "hal_conected")
    bad = edit(bad, b, "torque_nm: 0.0", "torque_nm: 3.0")
    bad = edit(bad, c, "mode: hold", "mode: hover")
    bad = edit(bad, d, "advance: [isb_limits_recorded, ", "advance: [")  # every later enforce_isb state is wrong
    bad = edit(
        bad,
        "fail",
        "reset: [faults_cleared, fault_acknowledged, arm_released]",
        "reset: [fault_acknowledged, arm_released]",
    )
    isb = [k for k, s in enumerate(SHIPPED_DATA["states"]) if s.get("enforce_isb")]
    assert isb
    assert min(isb) > d
    return bad, [
        Expect(line(bad, "hal_conected"), f"states.{a}.guards.advance.0", "unknown guard 'hal_conected'"),
        Expect(line(bad, "torque_nm: 3.0"), f"states.{b}.limits.torque_nm", "its torque limit must be 0, not 3"),
        Expect(line(bad, "mode: hover"), f"states.{c}.mode", "unknown mode 'hover'"),
        *(Expect(line(bad, "enforce_isb:", k), f"states.{k}.enforce_isb", "requires isb_limits_recorded") for k in isb),
        Expect(line(bad, "reset:", "fail"), "fail.guards.reset", "add faults_cleared"),
    ]


@case("several type errors at once")
def _several_types(text: str) -> tuple[str, list[Expect]]:
    a, b, c = IDX["settings"], IDX["pilot_installation"], IDX["rom_limits"]
    bad = edit(text, a, "fail_on_fault: true", "fail_on_fault: maybe")
    bad = edit(bad, b, "torque_nm: 10.0", 'torque_nm: "lots"')
    bad = edit(bad, c, "fail_on_fault: true\n", "fail_on_fault: true\n    colour: red\n")
    return bad, [
        Expect(line(bad, "maybe"), f"states.{a}.fail_on_fault", "valid boolean"),
        Expect(line(bad, '"lots"'), f"states.{b}.limits.torque_nm", "valid number"),
        Expect(line(bad, "colour: red"), f"states.{c}.colour", "Extra inputs are not permitted"),
    ]


# --- the safety invariants of the spec itself (docs/fsm.md, "Safety invariants of the spec") ---------


@case("torque limit above the drive's maximum")
def _torque_above_drive(text: str) -> tuple[str, list[Expect]]:
    i = IDX["compensation"]
    over = DEVICE.sea.max_motor_torque_nm + 10.0
    bad = edit(text, i, "torque_nm: 30.0", f"torque_nm: {over}")
    return bad, [
        Expect(
            line(bad, f"torque_nm: {over}"),
            f"states.{i}.limits.torque_nm",
            f"torque limit {over:g} Nm exceeds the drives' maximum motor torque of the DAROR-01, "
            f"{DEVICE.sea.max_motor_torque_nm:g} Nm",
            "torque within the drive",
        )
    ]


@case("velocity limit above every joint's device limit")
def _velocity_above_device(text: str) -> tuple[str, list[Expect]]:
    i = IDX["compensation"]
    fastest = max(DEVICE.limits.max_velocity_rad_s)
    bad = edit(text, i, "velocity_rad_s: 2.0", f"velocity_rad_s: {fastest + 0.5}")
    return bad, [
        Expect(
            line(bad, f"velocity_rad_s: {fastest + 0.5}"),
            f"states.{i}.limits.velocity_rad_s",
            f"exceeds every joint's speed limit of the DAROR-01 (at most {fastest:g} rad/s",
            "speed within the device",
        )
    ]


@case("first state applies torque")
def _first_state_torque(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, 0, "mode: torque_off", "mode: minimal_impedance")
    bad = edit(bad, 0, "torque_nm: 0.0", "torque_nm: 5.0")  # a consistent limit: only the order is wrong
    at = line(bad, "mode: minimal_impedance", 0)
    return bad, [
        Expect(
            at,
            "states.0.mode",
            "is the first state (entered at start-up and by every reset)",
            "first state torque-free",
        ),
        Expect(
            at,
            "states.0.mode",
            "comes before the first e-stop test state, 2 safety_check",
            "e-stops tested before torque",
        ),
    ]


@case("no e-stop test state at all")
def _no_test_state(text: str) -> tuple[str, list[Expect]]:
    """Every test state made an ordinary state (and its e-stop guards removed): torque is never preceded by a test."""
    bad = text
    for name in ("safety_check", "safety_experience", "operative_check"):
        k = IDX[name]
        bad = edit(bad, k, "fail_on_fault: false", "fail_on_fault: true")
        for guard in ("estop_operator_tested, ", "estop_pilot_tested, ", "estop_tested, "):
            if guard in _block(bad, k):
                bad = edit(bad, k, guard, "")
    torque = [k for k, s in enumerate(SHIPPED_DATA["states"]) if s["mode"] != "torque_off"]
    return bad, [
        Expect(line(bad, "mode:", k), f"states.{k}.mode", "no state tests the e-stops", "e-stops tested before torque")
        for k in torque
    ]


@case("test state advances with an e-stop pressed")
def _test_state_not_released(text: str) -> tuple[str, list[Expect]]:
    i = IDX["safety_experience"]
    bad = edit(text, i, "safety_experience_confirmed, estop_released,", "safety_experience_confirmed,")
    return bad, [
        Expect(
            line(bad, "advance:", i), f"states.{i}.guards.advance", "need estop_released", "test states end released"
        )
    ]


@case("hold without enforce_isb")
def _hold_no_isb(text: str) -> tuple[str, list[Expect]]:
    i = IDX["training"]
    bad = edit(text, i, "enforce_isb: true", "enforce_isb: false")
    return bad, [
        Expect(
            line(bad, "enforce_isb: false"),
            f"states.{i}.enforce_isb",
            "mode 'hold' moves the robot on its own (position control) and must stay inside the pilot's ISB limits",
            "position control inside the ISB limits",
        )
    ]


@case("torque outside the ISB limits after they were recorded")
def _isb_dropped(text: str) -> tuple[str, list[Expect]]:
    i = IDX["compensation"]
    bad = edit(text, i, "enforce_isb: true", "enforce_isb: false")
    return bad, [
        Expect(
            line(bad, "enforce_isb: false"),
            f"states.{i}.enforce_isb",
            "applies torque after the pilot's ISB limits were recorded but does not enforce them",
            "ISB limits stay enforced",
        )
    ]


@case("enforced ISB limits entered with the arm outside")
def _isb_entered_outside(text: str) -> tuple[str, list[Expect]]:
    i = IDX["rom_limits"]
    bad = edit(text, i, "isb_limits_recorded, arm_inside_isb_limits,", "isb_limits_recorded,")
    return bad, [
        Expect(
            line(bad, "advance:", i),
            f"states.{i}.guards.advance",
            "the advance from 6 rom_limits enters 7 operative_check, which enforces the ISB limits from its first "
            "tick: its guards need arm_inside_isb_limits",
            "ISB limits entered with the arm inside",
        )
    ]


@case("advance into compensation without a model approval")
def _unapproved_advance(text: str) -> tuple[str, list[Expect]]:
    i = IDX["rom_limits"]
    bad = edit(
        text,
        i,
        "advance: [isb_limits_recorded, arm_inside_isb_limits, compensation_model_approved,",
        "advance: [isb_limits_recorded, arm_inside_isb_limits,",
    )
    return bad, [
        Expect(
            line(bad, "advance:", i),
            f"states.{i}.guards.advance",
            "advancing from 6 rom_limits enters 7 operative_check, whose mode 'compensation' applies a compensation model",
            "only approved models compensate",
        )
    ]


@case("revert into compensation without a model approval")
def _unapproved_revert(text: str) -> tuple[str, list[Expect]]:
    i = IDX["identification"]
    bad = edit(text, i, "revert: [robot_at_rest, compensation_model_approved]", "revert: [robot_at_rest]")
    return bad, [
        Expect(
            line(bad, "revert:", i),
            f"states.{i}.guards.revert",
            "reverting from 8 identification enters 7 operative_check",
            "only approved models compensate",
        )
    ]


@case("advance into the last state without a validated model")
def _unvalidated_compensation(text: str) -> tuple[str, list[Expect]]:
    i = IDX["training"]
    bad = edit(text, i, "advance: [model_trained_and_validated, no_active_faults]", "advance: [no_active_faults]")
    return bad, [
        Expect(
            line(bad, "advance:", i),
            f"states.{i}.guards.advance",
            "advancing from 9 training enters 10 compensation",
            "only approved models compensate",
        )
    ]


# --- YAML and types: what a lax reader would have accepted ------------------------------------------


@case("a key written twice")
def _duplicate_key(text: str) -> tuple[str, list[Expect]]:
    """The defect that raised a state's torque limit from 10 to 30 Nm: the second ``limits:`` won silently."""
    i = IDX["pilot_installation"]
    first = "    limits: {torque_nm: 10.0, velocity_rad_s: 1.0}\n"
    bad = edit(text, i, first, first + "    limits: {torque_nm: 30.0, velocity_rad_s: 1.0}\n")
    return bad, [
        Expect(
            line(bad, "limits: {torque_nm: 30.0", i),
            f"states.{i}.limits",
            f"key 'limits' is written twice (first on line {line(bad, 'limits: {torque_nm: 10.0', i)})",
        )
    ]


@case("torque_nm true")
def _torque_true(text: str) -> tuple[str, list[Expect]]:
    i = IDX["pilot_installation"]
    bad = edit(text, i, "torque_nm: 10.0", "torque_nm: true")
    return bad, [
        Expect(
            line(bad, "torque_nm: true"),
            f"states.{i}.limits.torque_nm",
            "Input should be a valid number; got true (a yes/no value)",
        )
    ]


@case("torque_nm as quoted text")
def _torque_text(text: str) -> tuple[str, list[Expect]]:
    i = IDX["pilot_installation"]
    bad = edit(text, i, "torque_nm: 10.0", 'torque_nm: "10"')
    return bad, [
        Expect(line(bad, 'torque_nm: "10"'), f"states.{i}.limits.torque_nm", "valid number; got the text '10'")
    ]


@case("velocity limit not a number (.nan)")
def _velocity_nan(text: str) -> tuple[str, list[Expect]]:
    i = IDX["startup"]
    bad = edit(text, i, "velocity_rad_s: 2.0", "velocity_rad_s: .nan")
    return bad, [Expect(line(bad, "velocity_rad_s: .nan"), f"states.{i}.limits.velocity_rad_s", "finite number")]


@case("state number true")
def _number_true(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, 0, "number: 1\n", "number: true\n")
    return bad, [Expect(line(bad, "number: true"), "states.0.number", "valid integer; got true (a yes/no value)")]


@case("version true")
def _version_true(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, None, "\nversion: 1\n", "\nversion: true\n")
    return bad, [Expect(line(bad, "version: true"), "version", "Input should be a whole number; got true")]


@case("version 1.0")
def _version_float(text: str) -> tuple[str, list[Expect]]:
    bad = edit(text, None, "\nversion: 1\n", "\nversion: 1.0\n")
    return bad, [Expect(line(bad, "version: 1.0"), "version", "Input should be a whole number; got 1.0")]


@case("fail_on_fault 0")
def _fail_on_fault_zero(text: str) -> tuple[str, list[Expect]]:
    i = IDX["settings"]
    bad = edit(text, i, "fail_on_fault: true", "fail_on_fault: 0")
    return bad, [Expect(line(bad, "fail_on_fault: 0"), f"states.{i}.fail_on_fault", "valid boolean; got 0")]


@pytest.mark.parametrize("name", list(CASES))
def test_malformed_spec_is_refused_with_file_line_and_field(name: str, tmp_path: Path) -> None:
    bad, expected = CASES[name](SHIPPED_TEXT)
    assert bad != SHIPPED_TEXT
    path = tmp_path / "fsm_spec.yaml"
    path.write_text(bad, encoding="utf-8")
    assert_problems(path, expected)


def test_enough_malformed_specs() -> None:
    assert len(CASES) >= 14


def _invariant_cases() -> dict[str, list[str]]:
    """Invariant name -> the cases whose expected problems name it."""
    covered: dict[str, list[str]] = {}
    for name, make in CASES.items():
        for want in make(SHIPPED_TEXT)[1]:
            if want.invariant is not None:
                covered.setdefault(want.invariant, []).append(name)
    return covered


INVARIANT_CASES = sorted({name for names in _invariant_cases().values() for name in names})


def test_every_safety_invariant_has_a_malformed_spec() -> None:
    assert set(_invariant_cases()) == set(INVARIANTS)


def test_every_safety_invariant_is_in_the_docs_table() -> None:
    """docs/fsm.md, "Safety invariants of the spec": one row per invariant, in the order they are declared."""
    text = (DEFAULT_SPEC_PATH.parent / "docs" / "fsm.md").read_text(encoding="utf-8")
    start = text.index("### Safety invariants of the spec")
    section = text[start : text.index("\n## ", start)]
    rows = [r for r in section.splitlines() if r.startswith("| **")]
    named = [r.split("**")[1] for r in rows]
    assert named == list(INVARIANTS)


@pytest.mark.parametrize("name", INVARIANT_CASES)
def test_cli_check_names_the_violated_invariant(name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad, expected = CASES[name](SHIPPED_TEXT)
    path = tmp_path / "bad_spec.yaml"
    path.write_text(bad, encoding="utf-8")
    capsys.readouterr()
    assert run("fsm", "check", path) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert "Traceback" not in err
    lines = err.rstrip("\n").split("\n")
    assert lines[0].startswith(f"daror fsm check: error: {path}: line ")
    assert len(lines) == len(expected)
    for want in expected:
        prefix = f"{path}: line {want.line}, field {want.field}: "
        assert any(prefix in x and want.fragment in x for x in lines), (prefix, err)
        if want.invariant is not None:
            assert f"[safety invariant: {want.invariant}]" in err


def test_the_drive_maximum_itself_is_allowed(tmp_path: Path) -> None:
    i = IDX["compensation"]
    top = DEVICE.sea.max_motor_torque_nm
    path = tmp_path / "spec.yaml"
    path.write_text(edit(SHIPPED_TEXT, i, "torque_nm: 30.0", f"torque_nm: {top}"), encoding="utf-8")
    assert load_fsm_spec(path).states[i].limits.torque_nm == top


def test_an_int_where_a_float_is_meant_is_fine(tmp_path: Path) -> None:
    i = IDX["pilot_installation"]
    path = tmp_path / "spec.yaml"
    path.write_text(edit(SHIPPED_TEXT, i, "torque_nm: 10.0", "torque_nm: 10"), encoding="utf-8")
    assert load_fsm_spec(path) == load_fsm_spec()


def test_limits_are_checked_against_the_given_robot(tmp_path: Path) -> None:
    """A robot with weaker drives (20 Nm): the shipped spec's 30 Nm states are refused, each named."""
    weak = DEVICE.model_copy(update={"sea": DEVICE.sea.model_copy(update={"max_motor_torque_nm": 20.0})})
    with pytest.raises(FsmSpecError) as info:
        load_fsm_spec(DEFAULT_SPEC_PATH, description=weak)
    over = [k for k, s in enumerate(SHIPPED_DATA["states"]) if s["limits"]["torque_nm"] > 20.0]
    assert over
    lines = str(info.value).splitlines()
    assert len(lines) == len(over)
    for k, row in zip(over, lines, strict=True):
        assert f"field states.{k}.limits.torque_nm: " in row
        assert row.endswith("[safety invariant: torque within the drive]")


def _ss1(relay_delay_s: float) -> object:
    return DEVICE.model_copy(
        update={"estop": DEVICE.estop.model_validate({"wiring": "ss1", "relay_delay_s": relay_delay_s})}
    )


def test_an_estop_lowering_fits_inside_the_ss1_relay_of_the_given_robot(tmp_path: Path) -> None:
    """With the buttons wired for a safe stop 1 the e-stop may lower the arm, within the relay's delay, not longer."""
    path = tmp_path / "fsm_spec.yaml"
    path.write_text(
        edit(SHIPPED_TEXT, "fault_reactions", 'estop: {reaction: "off"}', "estop: {reaction: lower, within_s: 8.0}")
    )
    spec = load_fsm_spec(path, description=_ss1(10.0))  # type: ignore[arg-type]
    assert spec.fault_reactions[FaultKind.ESTOP].within_s == 8.0
    with pytest.raises(FsmSpecError) as info:
        load_fsm_spec(path, description=_ss1(5.0))  # type: ignore[arg-type]
    (row,) = str(info.value).splitlines()
    assert (
        f"line {line(path.read_text(), 'estop: {', 'fault_reactions')}, field fault_reactions.estop.within_s: " in row
    )
    assert "may take 8 s but the safety relay of the DAROR-01 cuts the power 5 s after a press" in row
    assert row.endswith("[safety invariant: e-stops stop in category 0 or 1]")
    # the shipped spec (off) is fine with either wiring: a category 0 stop is always allowed
    load_fsm_spec(DEFAULT_SPEC_PATH, description=_ss1(5.0))  # type: ignore[arg-type]


# --- files that are not a spec at all --------------------------------------------------------


def _yaml_error(path: Path) -> str:
    with pytest.raises(FsmSpecError) as info:
        load_fsm_spec(path)
    return str(info.value)


def test_bad_yaml_names_line_and_column(tmp_path: Path) -> None:
    bad = edit(SHIPPED_TEXT, IDX["settings"], "name: settings", "name: settings: again")
    path = tmp_path / "spec.yaml"
    path.write_text(bad, encoding="utf-8")
    row = line(bad, "name: settings: again")
    column = bad.splitlines()[row - 1].index("settings:") + len("settings:")  # the second colon, 1-based
    assert (
        _yaml_error(path)
        == f"{path}: line {row}, column {column}: not valid YAML (mapping values are not allowed here)"
    )


def test_tab_indentation_names_line_and_column(tmp_path: Path) -> None:
    bad = edit(SHIPPED_TEXT, "fail", "  mode: torque_off", "\tmode: torque_off")
    path = tmp_path / "spec.yaml"
    path.write_text(bad, encoding="utf-8")
    message = _yaml_error(path)
    assert message.startswith(f"{path}: line {line(bad, chr(9) + 'mode')}, column 1: not valid YAML (")
    assert "'\\t'" in message


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n"])
def test_empty_file(tmp_path: Path, text: str) -> None:
    path = tmp_path / "empty.yaml"
    path.write_text(text, encoding="utf-8")
    assert _yaml_error(path) == f"{path}: file is empty; expected a YAML mapping"


def test_list_instead_of_mapping(tmp_path: Path) -> None:
    path = tmp_path / "list.yaml"
    path.write_text("- version: 1\n- states: []\n", encoding="utf-8")
    assert (
        _yaml_error(path)
        == f"{path}: line 1: expected a mapping with version, superstates, states and fail; found a list"
    )


def test_list_after_the_header_names_its_line(tmp_path: Path) -> None:
    header = SHIPPED_TEXT[: SHIPPED_TEXT.index("\nversion:") + 1]
    text = header + "- version: 1\n- states: []\n"
    path = tmp_path / "list.yaml"
    path.write_text(text, encoding="utf-8")
    assert _yaml_error(path).startswith(f"{path}: line {line(text, '- version: 1')}: expected a mapping")


def test_scalar_instead_of_mapping(tmp_path: Path) -> None:
    path = tmp_path / "scalar.yaml"
    path.write_text("just some words\n", encoding="utf-8")
    assert _yaml_error(path).startswith(f"{path}: line 1: expected a mapping")


def test_file_not_found(tmp_path: Path) -> None:
    path = tmp_path / "missing.yaml"
    assert _yaml_error(path) == f"{path}: file not found"


def test_error_is_an_input_error() -> None:
    from daror_runtime.errors import InputError

    assert issubclass(FsmSpecError, InputError)


# --- the shipped spec and its schema ---------------------------------------------------------


def test_shipped_spec_loads() -> None:
    spec = load_fsm_spec()
    assert spec == load_fsm_spec(DEFAULT_SPEC_PATH)
    assert len(spec.states) == 10
    assert [s.number for s in spec.states] == list(range(1, 11))
    assert [s.name for s in spec.states] == list(IDX)
    assert spec.fail.name == "FAIL"
    assert spec.fail.mode == "torque_off"
    assert set(spec.fail.guards.reset) >= {"faults_cleared", "fault_acknowledged"}
    assert [s.number for s in spec.test_states] == [2, 5, 7]
    assert [s.name for s in spec.test_states] == ["safety_check", "safety_experience", "operative_check"]
    assert spec.first.name == "startup"
    assert [s.name for s in spec.superstates] == ["pre_op", "installation", "operative"]
    for state in spec.states:
        assert state.mode in MODES
        assert all(g in GUARDS for kind in ("advance", "revert", "reset") for g in getattr(state.guards, kind))


def test_committed_schema_is_current() -> None:
    committed = SCHEMA_PATH.read_text(encoding="utf-8")
    assert committed == spec_json_schema_text(), (
        "fsm_spec.schema.json is stale: run `daror fsm schema --out fsm_spec.schema.json`"
    )


def test_schema_lists_the_registered_names() -> None:
    text = spec_json_schema_text()
    schema = json.loads(text)
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert set(schema["required"]) == {"version", "superstates", "states", "fail", "fault_reactions", "drive_reactions"}
    for name in [*GUARDS, *MODES, *(kind.value for kind in FaultKind)]:
        assert f'"{name}"' in text


def test_schema_validates_the_shipped_spec_and_refuses_a_typo() -> None:
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(SCHEMA_PATH.read_text(encoding="utf-8"))
    jsonschema.validate(SHIPPED_DATA, schema)
    bad = yaml.safe_load(edit(SHIPPED_TEXT, 0, "fail_on_fault: true", "fail_on_falt: true"))
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, schema)


def test_model_validates_the_shipped_data() -> None:
    assert FsmSpec.model_validate(SHIPPED_DATA) == load_fsm_spec()


# --- the CLI ---------------------------------------------------------------------------------


def run(*argv: object) -> int:
    return main([str(a) for a in argv])


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_cli_check_shipped(capsys: pytest.CaptureFixture[str]) -> None:
    assert run("fsm", "check") == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert f"{DEFAULT_SPEC_PATH}: valid (10 states in 3 superstates, and FAIL)" in out
    for name in [*IDX, "FAIL"]:
        assert name in out
    assert run("fsm", "check", DEFAULT_SPEC_PATH) == 0
    assert capsys.readouterr().out == out


def test_cli_check_states_table_shows_full_names(capsys: pytest.CaptureFixture[str]) -> None:
    assert run("fsm", "check") == 0
    out = capsys.readouterr().out
    for number, name in enumerate(IDX, start=1):
        rows = [x for x in out.splitlines() if re.match(rf"^│ {number}\s+│", x)]
        assert len(rows) == 1, rows
        assert f" {name} " in rows[0], rows


@pytest.mark.parametrize("name", ["unknown guard", "FAIL reset without fault_acknowledged", "misspelt field"])
def test_cli_check_bad_spec(name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad, expected = CASES[name](SHIPPED_TEXT)
    path = write(tmp_path, "bad_spec.yaml", bad)
    assert run("fsm", "check", path) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith(f"daror fsm check: error: {path}: line ")
    for want in expected:
        assert f"{path}: line {want.line}, field {want.field}: " in err


def test_cli_check_bad_yaml_and_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, "broken.yaml", "version: [1\n")
    assert run("fsm", "check", path) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"daror fsm check: error: {path}: line ")
    assert "not valid YAML" in err
    missing = tmp_path / "nowhere.yaml"
    assert run("fsm", "check", missing) == 2
    assert capsys.readouterr().err == f"daror fsm check: error: {missing}: file not found\n"


def _check_mermaid(text: str) -> None:
    spec = load_fsm_spec()
    rows = text.splitlines()
    assert rows[0] == "stateDiagram-v2"
    assert f"    [*] --> {spec.first.name}" in rows
    for superstate in spec.superstates:
        assert f'    state "{superstate.name}" as {superstate.name} {{' in rows
    for state in spec.states:
        assert any(r.startswith(f"        {state.name}: {state.number} {state.name}") for r in rows), state.name
        edges = [r for r in rows if r.startswith(f"    {state.name} --> FAIL")]
        if state.fail_on_fault:
            assert edges == [f"    {state.name} --> FAIL: fault"]
        else:
            assert edges == [], f"test state {state.name} must not fail"
        following = spec.next_state(state)
        if following is not None:
            assert any(r.startswith(f"    {state.name} --> {following.name}: advance") for r in rows)
    assert sum(" --> FAIL: fault" in r for r in rows) == sum(s.fail_on_fault for s in spec.states) == 7
    assert "    FAIL --> startup: reset [faults_cleared, fault_acknowledged, arm_released]" in rows


def test_cli_diagram_stdout(capsys: pytest.CaptureFixture[str]) -> None:
    assert run("fsm", "diagram") == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert out == mermaid(load_fsm_spec())
    _check_mermaid(out)


def test_cli_diagram_out_and_bad_spec(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "docs" / "fsm.mmd"
    target.parent.mkdir()  # the command writes into an existing folder only
    assert run("fsm", "diagram", "--out", target) == 0
    assert f"wrote {target}" in capsys.readouterr().out
    _check_mermaid(target.read_text(encoding="utf-8"))
    assert sorted(p.name for p in target.parent.iterdir()) == ["fsm.mmd"]  # no temporary file left

    bad, _ = CASES["unknown mode"](SHIPPED_TEXT)
    spec = write(tmp_path, "bad.yaml", bad)
    fresh = tmp_path / "out" / "fsm.mmd"
    fresh.parent.mkdir()
    assert run("fsm", "diagram", spec, "--out", fresh) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith(f"daror fsm diagram: error: {spec}: line ")
    assert not fresh.exists()
    before = target.read_text(encoding="utf-8")
    assert run("fsm", "diagram", spec, "--out", target) == 2
    capsys.readouterr()
    assert target.read_text(encoding="utf-8") == before  # the previous diagram is untouched
    assert sorted(p.name for p in target.parent.iterdir()) == ["fsm.mmd"]


def test_cli_schema(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run("fsm", "schema") == 0
    assert capsys.readouterr().out == spec_json_schema_text()
    target = tmp_path / "fsm_spec.schema.json"
    assert run("fsm", "schema", "--out", target) == 0
    capsys.readouterr()
    assert target.read_text(encoding="utf-8") == SCHEMA_PATH.read_text(encoding="utf-8")
