"""The diagram of a spec, generated (Appendix A's lost Fig. A.1, regenerated from ``fsm_spec.yaml``).

Mermaid ``stateDiagram-v2``: it renders in the Markdown viewers of GitHub and GitLab and in most
editors without another tool, and it is text, so a change of the spec shows in a review as a
change of the diagram. Superstates are composite states; every edge is labelled with its event
and guards. Reset edges are drawn only where a state has reset guards (every state may reset to
the first state; a note says so instead of ten unlabelled arrows).
"""

from __future__ import annotations

from daror_runtime.fsm.machine import Event, transition_table
from daror_runtime.fsm.spec import FsmSpec, StateSpec


def _state_text(state: StateSpec) -> str:
    test = ", e-stop test" if not state.fail_on_fault else ""
    isb = ", ISB limits" if state.enforce_isb else ""
    limits = f"{state.limits.torque_nm:g} Nm, {state.limits.velocity_rad_s:g} rad/s"
    return f"{state.number} {state.name}{test}<br/>{state.mode}, {limits}{isb}"


def _edge_text(event: Event, guards: tuple[str, ...]) -> str:
    return event.value if not guards else f"{event.value} [{', '.join(guards)}]"


def mermaid(spec: FsmSpec) -> str:
    """The Mermaid source of ``spec``'s diagram (ends with a newline)."""
    lines = ["stateDiagram-v2", "    direction TB", f"    [*] --> {spec.first.name}"]
    for superstate in spec.superstates:
        members = [s for s in spec.states if s.superstate == superstate.name]
        lines.append(f'    state "{superstate.name}" as {superstate.name} {{')
        lines.extend(f"        {s.name}: {_state_text(s)}" for s in members)
        lines.append("    }")
    fail = spec.fail
    lines.append(f"    {fail.name}: {fail.name}<br/>{fail.mode}")
    table = transition_table(spec)
    for (source, event), t in table.items():
        if source == fail.name:
            continue  # drawn last, below the fault edges
        if event in (Event.ADVANCE, Event.REVERT) or (event == Event.RESET and t.guards):
            lines.append(f"    {source} --> {t.dest}: {_edge_text(event, t.guards)}")
    for state in spec.states:
        if (state.name, Event.FAIL) in table:
            lines.append(f"    {state.name} --> {fail.name}: fault")
    reset = table[(fail.name, Event.RESET)]
    lines.append(f"    {fail.name} --> {spec.first.name}: {_edge_text(Event.RESET, reset.guards)}")
    tests = ", ".join(str(s.number) for s in spec.test_states) or "none"
    lines += [
        f"    note right of {spec.first.name}",
        f"        reset from every state returns to {spec.first.number} {spec.first.name}",
        f"        e-stop test states ({tests}): a fault removes torque and is recorded, no {fail.name}",
        "    end note",
    ]
    return "\n".join(lines) + "\n"
