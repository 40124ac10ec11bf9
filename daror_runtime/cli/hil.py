"""``daror hil``: hardware-in-the-loop, a console script over simulated CANopen drives (docs/canopen.md)."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from rich.console import Console

from daror_runtime.cli.common import CommandParser, Commands, UsageError, bind, output_dir
from daror_runtime.cli.console import run_console_session
from daror_runtime.errors import DarorError, InputError

#: ``--fault KIND:NODE@T_S``: a drive's fault, its node id, the robot time it happens at; ``--fault KIND@T_S``:
#: a fault of the bus itself (the master's controller: bus_off, error_passive).
_FAULT_RE = re.compile(r"^(?P<kind>[a-z_]+)(?::(?P<node>\d{1,3}))?@(?P<at>[0-9]+(?:\.[0-9]*)?)$")


def register(commands: Commands) -> None:
    """``daror hil`` on ``commands``; its flags declared when it is used (the fault kinds' registry imports numpy)."""
    hil = commands.add_parser(
        "hil",
        help="hardware-in-the-loop: a console script over simulated CANopen drives (lock-step), with the bus log",
    )
    hil.declare_on_use(_declare_flags)
    bind(hil, cmd_hil)


def _declare_flags(hil: CommandParser) -> None:
    """The flags of ``daror hil``; ``--fault``'s kinds are those the simulated bus offers (:mod:`hal.capabilities`)."""
    from hal.capabilities import BUS_FAULT_KINDS, BUS_LINE_FAULT_KINDS

    hil.add_argument("--script", type=Path, required=True, help="console lines, all checked before anything runs")
    hil.add_argument("--out", type=Path, required=True, help="folder: can.log, hil.json, the session and audit files")
    hil.add_argument("--rate-hz", type=float, help="loop and SYNC rate (default: the highest the bus load allows)")
    hil.add_argument("--scenario", help="simulated plant behind the drives (default exo_dummy_arm)")
    hil.add_argument(
        "--fault",
        action="append",
        metavar="KIND:NODE@T_S",
        help=f"inject a bus fault into node NODE at robot time T_S (repeatable); KIND: {', '.join(BUS_FAULT_KINDS)}; "
        f"or a fault of the bus itself, KIND@T_S: {', '.join(BUS_LINE_FAULT_KINDS)}",
    )
    hil.add_argument("--settings", type=Path, help="session settings YAML (default: the built-in settings)")
    hil.add_argument("--spec", type=Path, help="FSM spec (default: fsm_spec.yaml of the repository)")
    hil.add_argument(
        "--hal-config",
        type=Path,
        help="robot file (backend can or can-sim): its nodes run on simulated drives built from their EDS "
        "(default: the DAROR-01's four drives)",
    )


def _parse_fault(
    text: str, node_ids: list[int], kinds: tuple[str, ...], bus_kinds: tuple[str, ...] = ()
) -> tuple[str, int, float]:
    """``(kind, joint 1-4, robot time s)`` of one ``--fault KIND:NODE@T_S``; joint 0 for ``--fault BUS_KIND@T_S``.

    Raises:
        UsageError: not of that form, an unknown kind, a node that is not one of the drives', a
            drive's fault without a node or a bus fault with one.
    """
    match = _FAULT_RE.match(text)
    if match is None:
        raise UsageError(
            f"--fault {text!r}: expected KIND:NODE@T_S or a bus fault KIND@T_S, e.g. heartbeat_loss:2@30.5"
        )
    kind, at = match["kind"], float(match["at"])
    if kind not in kinds and kind not in bus_kinds:
        raise UsageError(f"--fault {text!r}: unknown fault {kind!r}; expected one of {', '.join((*kinds, *bus_kinds))}")
    if kind in bus_kinds:
        if match["node"] is not None:
            raise UsageError(f"--fault {text!r}: {kind} is a fault of the bus, not of a node: expected {kind}@T_S")
        return kind, 0, at
    if match["node"] is None:
        raise UsageError(f"--fault {text!r}: {kind} is a drive's fault: expected {kind}:NODE@T_S")
    node = int(match["node"])
    if node not in node_ids:
        raise UsageError(f"--fault {text!r}: node {node} is not a drive; expected one of {node_ids}")
    return kind, node_ids.index(node) + 1, at


def cmd_hil(args: argparse.Namespace, console: Console) -> int:
    """A console script over simulated CANopen drives, lock-step: the session, the audit log and the bus log.

    Once the run has started, its files are written whatever the session or the script did:
    ``hil.json`` says which faults were injected, when, and how the robot reacted
    (:mod:`daror_runtime.hil`), and a failed script still exits 1 after it.
    """
    from daror_runtime.clocks import LockStepClock
    from daror_runtime.console.commands import parse_context
    from daror_runtime.console.grammar import check_lines
    from daror_runtime.console.run import read_script
    from daror_runtime.fsm.spec import load_fsm_spec
    from daror_runtime.hil import (
        ScheduledFault,
        fault_lines,
        fault_summaries,
        hil_config,
        let_the_reaction_play_out,
        read_audit,
    )
    from daror_runtime.session.settings import load_session_settings
    from daror_runtime.util.atomic import write_text_atomic
    from daror_runtime.util.outputs import output_lock
    from hal.capabilities import BUS_FAULT_KINDS, BUS_LINE_FAULT_KINDS, BusStatistics, FaultSchedule
    from hal.interface import open_hal

    spec = load_fsm_spec(args.spec)
    settings = load_session_settings(args.settings)
    out = output_dir(args.out, args.script)
    traffic = out / "can.log.gz"  # compressed as it is written (D137): zcat can.log.gz | canplayer
    for name in (traffic, out / "can.log", out / "hil.json"):
        if name.exists():
            raise UsageError(f"{name}: exists; a HIL run writes a new one: expected another --out")
    config = hil_config(args.hal_config, args.scenario, args.rate_hz, traffic)
    faults = [
        _parse_fault(text, list(config.node_ids), BUS_FAULT_KINDS, BUS_LINE_FAULT_KINDS) for text in args.fault or []
    ]
    hal = open_hal(config)
    world = hal.world
    if not isinstance(world, FaultSchedule) or not isinstance(hal, BusStatistics):
        raise UsageError(f"the {config.backend} backend schedules no faults")  # the registry was changed
    checked = check_lines(
        read_script(args.script), str(args.script), parse_context(spec, hal.description, world.fault_kinds)
    )
    for kind, joint, at_s in faults:
        world.schedule_fault(kind, joint, at_s)
    clock = LockStepClock(1.0 / hal.rate_hz)
    scheduled = [ScheduledFault(k, config.node_ids[j - 1] if j else None, j, t) for k, j, t in faults]
    with output_lock(out):
        code, error = 1, None
        try:
            code = run_console_session(
                args, console, hal, out, spec, settings, checked, False, clock,
                after_script=lambda runtime, session: let_the_reaction_play_out(
                    runtime, session.say, session.show_announcements
                ),
            )  # fmt: skip
        except DarorError as exc:  # a failed script or session: its files are written all the same, then exit 1
            code, error = (2 if isinstance(exc, InputError) else 1), str(exc)
            raise
        finally:  # the session is closed (torque off, session.json, the bus log): what it did, in hil.json
            audit_path = out / "audit.jsonl"  # the session's own; else where --log-json sent its lines
            audit = read_audit(audit_path if audit_path.exists() or args.log_json is None else args.log_json)
            summaries = fault_summaries(
                scheduled, world.drive_events(), audit, spec, list(config.node_ids), hal.rate_hz
            )
            report = {
                "script": str(args.script),
                "exit_code": code,
                "error": error,
                "faults": summaries,
                "bus": hal.bus_report(),
            }
            write_text_atomic(out / "hil.json", json.dumps(report, indent=2, default=str) + "\n")
            for line in fault_lines(summaries):
                console.print(line, soft_wrap=True)
            frames = report["bus"].get("frames_sent", 0)  # type: ignore[union-attr]
            console.print(f"hil.json: {out / 'hil.json'}; bus log: {traffic} ({frames} frames sent)")
    return code
