"""``daror fsm check|diagram|schema``: the safety FSM spec checked, drawn, its JSON Schema (docs/fsm.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rich.console import Console

from daror_runtime.cli.common import Commands, bind, output_file


def register(commands: Commands) -> None:
    """``daror fsm check``, ``daror fsm diagram`` and ``daror fsm schema`` on ``commands``."""
    fsm = commands.add_parser("fsm", help="the safety FSM spec: check it, draw it, export its JSON Schema")
    fsm_cmds = fsm.add_subparsers(dest="fsm_command", required=True, metavar="WHAT")
    check = fsm_cmds.add_parser("check", help="validate a spec and print its states and transitions")
    check.add_argument("spec", nargs="?", type=Path, help="spec file (default: fsm_spec.yaml of the repository)")
    bind(check, cmd_fsm_check)
    diagram = fsm_cmds.add_parser("diagram", help="the spec as a Mermaid state diagram (docs/fsm.md)")
    diagram.add_argument("spec", nargs="?", type=Path, help="spec file (default: fsm_spec.yaml of the repository)")
    diagram.add_argument("--out", type=Path, help="write here instead of standard output")
    bind(diagram, cmd_fsm_diagram)
    schema = fsm_cmds.add_parser("schema", help="the JSON Schema of fsm_spec.yaml (for editors)")
    schema.add_argument("--out", type=Path, help="write here instead of standard output")
    bind(schema, cmd_fsm_schema)


def cmd_fsm_check(args: argparse.Namespace, console: Console) -> int:
    """Validate a spec and print its states and transitions.

    Raises:
        FsmSpecError: the spec is not valid (the file, the line and the field of each problem; exit 2).
    """
    from rich.table import Table

    from daror_runtime.fsm.machine import Event, transition_table
    from daror_runtime.fsm.spec import DEFAULT_SPEC_PATH, load_fsm_spec

    path = args.spec or DEFAULT_SPEC_PATH
    spec = load_fsm_spec(path)
    console.print(
        f"{path}: valid ({len(spec.states)} states in {len(spec.superstates)} superstates, and {spec.fail.name})"
    )
    states = Table(title="states")
    for column in ("#", "superstate", "state", "mode", "torque Nm", "speed rad/s", "fault enters FAIL", "ISB limits"):
        states.add_column(column, overflow="fold", no_wrap=column in ("state", "mode"))
    for s in spec.states:
        states.add_row(
            str(s.number), s.superstate, s.name, s.mode, f"{s.limits.torque_nm:g}", f"{s.limits.velocity_rad_s:g}",
            "yes" if s.fail_on_fault else "no (e-stop test)", "yes" if s.enforce_isb else "no",
        )  # fmt: skip
    states.add_row("F", "-", spec.fail.name, spec.fail.mode, "0", "-", "-", "-")
    console.print(states)
    transitions = Table(title="transitions (every guard must hold; advance also needs the operator's press)")
    for column in ("from", "event", "to", "guards"):
        transitions.add_column(column)
    for (source, event), t in transition_table(spec).items():
        dest = "(stays)" if event == Event.ACKNOWLEDGE else t.dest
        transitions.add_row(source, event.value, dest, ", ".join(t.guards) or "-")
    console.print(transitions)
    return 0


def cmd_fsm_diagram(args: argparse.Namespace, console: Console) -> int:
    """The spec as a Mermaid state diagram, to standard output or ``--out``."""
    from daror_runtime.fsm.diagram import mermaid
    from daror_runtime.fsm.spec import load_fsm_spec

    return _emit(mermaid(load_fsm_spec(args.spec)), args.out, console)


def cmd_fsm_schema(args: argparse.Namespace, console: Console) -> int:
    """The JSON Schema of ``fsm_spec.yaml``, to standard output or ``--out``."""
    from daror_runtime.fsm.spec import spec_json_schema_text

    return _emit(spec_json_schema_text(), args.out, console)


def _emit(text: str, out: Path | None, console: Console) -> int:
    """``text`` to standard output, or atomically to ``out``."""
    from daror_runtime.util.atomic import write_text_atomic

    if out is None:
        sys.stdout.write(text)
    else:
        write_text_atomic(output_file(out), text)
        console.print(f"wrote {out}")
    return 0
