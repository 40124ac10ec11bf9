"""The reaction a set of faults commands (daror_runtime/safety/reactions.py): properties over random faults.

Hypothesis draws faults (kinds, joints), the state they are found in, the e-stop wiring and the drives'
states, against the shipped spec and against specs whose reactions are drawn at random (every one
the checker accepts). The plan must be the spec's, never softer than any fault asks, and a reaction
under way only ever gets stricter.
"""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daror_runtime.fsm.spec import (
    BLIND_KINDS,
    MODEL_SUSPECT_KINDS,
    UNTRUSTED_JOINT_KINDS,
    FaultReaction,
    load_fsm_spec,
)
from daror_runtime.safety.faults import Fault, FaultKind
from daror_runtime.safety.reactions import CATEGORY, ReactionPlan, escalate, plan_reaction
from hal.interface import DriveState

SPEC = load_fsm_spec()
STATES = [s.name for s in SPEC.states]
RANK = {"hold": 0, "lower": 1, "off": 2}

faults = st.lists(
    st.builds(
        lambda kind, joint: Fault(kind, 1.0, f"{kind.value} (test)", joint),
        st.sampled_from(list(FaultKind)),
        st.one_of(st.none(), st.integers(1, 4)),
    ),
    min_size=1,
    max_size=5,
)
drives = st.tuples(*[st.sampled_from(list(DriveState))] * 4)
enabled = (DriveState.ENABLED,) * 4


@st.composite
def reaction_tables(draw: Any) -> dict[FaultKind, FaultReaction]:
    """Reactions a spec may declare: any, within the checker's invariants."""
    table = {}
    for kind in FaultKind:
        if kind in BLIND_KINDS:
            reaction = "off"
        elif kind == FaultKind.ESTOP:
            reaction = draw(st.sampled_from(["off", "lower"]))
        else:
            reaction = draw(st.sampled_from(["off", "lower", "hold"]))
        states = (
            {}
            if kind in BLIND_KINDS
            else draw(st.dictionaries(st.sampled_from(STATES), st.sampled_from(["off", "lower", "hold"]), max_size=2))
        )
        if kind == FaultKind.ESTOP:
            states = {s: r for s, r in states.items() if r != "hold"}
        table[kind] = FaultReaction(
            reaction=reaction,
            faulted_joint="off" if kind in UNTRUSTED_JOINT_KINDS else draw(st.sampled_from(["off", "with_the_arm"])),
            support="a_priori" if kind in MODEL_SUSPECT_KINDS else draw(st.sampled_from(["model", "a_priori"])),
            within_s=draw(st.floats(0.5, 30.0)) if kind == FaultKind.ESTOP else None,
            states=states,
        )
    return table


@settings(max_examples=500, deadline=None)
@given(found=faults, state=st.sampled_from(STATES), wiring=st.sampled_from(["sto", "ss1"]), now=drives)
def test_the_plan_is_the_spec_s_and_never_softer_than_any_fault_asks(
    found: list[Fault], state: str, wiring: str, now: tuple[DriveState, ...]
) -> None:
    plan = plan_reaction(found, state, SPEC.fault_reactions, wiring, now)
    for fault in found:
        entry = SPEC.fault_reactions[fault.kind]
        asked = entry.in_state(state)
        if fault.kind == FaultKind.ESTOP and wiring == "sto":
            asked = "off"
        assert RANK[plan.reaction] >= RANK[asked], (fault, plan)
        if entry.faulted_joint == "off":  # untrusted: that joint (every joint, if it names none) off
            named = {fault.joint} if fault.joint is not None else {1, 2, 3, 4}
            assert named <= set(plan.joints_off) or plan.reaction == "off"
        if entry.support == "a_priori":
            assert plan.support == "a_priori"
    # a joint whose drive held nothing gets no torque from a reaction
    assert {j + 1 for j, d in enumerate(now) if d != DriveState.ENABLED} <= set(plan.joints_off)
    if len(plan.joints_off) == 4:
        assert plan.reaction == "off"
    assert plan.category == CATEGORY[plan.reaction]
    assert plan.holds == (plan.reaction != "off")
    assert plan.within_s is None or plan.reaction == "lower"
    assert set(plan.causes) == {f"{f.kind.value} {f.joint}" if f.joint is not None else f.kind.value for f in found}


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(table=reaction_tables(), found=faults, state=st.sampled_from(STATES), wiring=st.sampled_from(["sto", "ss1"]))
def test_any_checked_spec_s_reaction_is_followed(
    table: dict[FaultKind, FaultReaction], found: list[Fault], state: str, wiring: str
) -> None:
    plan = plan_reaction(found, state, table, wiring, enabled)
    strictest = max(
        ("off" if f.kind == FaultKind.ESTOP and wiring == "sto" else table[f.kind].in_state(state) for f in found),
        key=RANK.__getitem__,
    )
    assert plan.reaction == strictest or (plan.reaction == "off" and len(plan.joints_off) == 4)
    estops = [table[f.kind].within_s for f in found if f.kind == FaultKind.ESTOP]
    if plan.reaction == "lower" and estops and wiring == "ss1" and strictest == "lower":
        assert plan.within_s == min(estops)


@settings(max_examples=500, deadline=None)
@given(
    first=faults,
    later=st.lists(faults, min_size=1, max_size=4),
    state=st.sampled_from(STATES),
    wiring=st.sampled_from(["sto", "ss1"]),
)
def test_a_reaction_under_way_only_gets_stricter(
    first: list[Fault], later: list[list[Fault]], state: str, wiring: str
) -> None:
    plan: ReactionPlan = plan_reaction(first, state, SPEC.fault_reactions, wiring, enabled)
    for batch in later:
        new = plan_reaction(batch, state, SPEC.fault_reactions, wiring, enabled)
        combined = escalate(plan, new)
        assert RANK[combined.reaction] >= max(RANK[plan.reaction], RANK[new.reaction])
        assert set(plan.joints_off) | set(new.joints_off) <= set(combined.joints_off)
        assert combined.support == ("a_priori" if "a_priori" in (plan.support, new.support) else "model")
        assert set(plan.causes) <= set(combined.causes)
        assert escalate(combined, new) == combined  # nothing new: nothing changes
        plan = combined


def test_an_estop_on_safe_torque_off_is_off_and_a_drive_fault_takes_only_its_joint() -> None:
    """Two cases by name: what the DAROR-01 does on its own wiring."""
    estop = plan_reaction(
        [Fault(FaultKind.ESTOP, 1.0, "pressed")], "compensation", SPEC.fault_reactions, "sto", enabled
    )
    assert (estop.reaction, estop.category, estop.joints_off) == ("off", 0, ())
    drive = plan_reaction(
        [Fault(FaultKind.DRIVE, 1.0, "drive 2", 2)], "compensation", SPEC.fault_reactions, "sto", enabled
    )
    assert (drive.reaction, drive.joints_off, drive.causes) == ("lower", (2,), ("drive 2",))
    software = plan_reaction(
        [Fault(FaultKind.SOFTWARE, 1.0, "raised")], "identification", SPEC.fault_reactions, "sto", enabled
    )
    assert (software.reaction, software.support) == ("lower", "a_priori")
