"""``daror can scan|check|zero|tare``: commissioning a CAN bus (docs/canopen.md, Commissioning).

Each handler prints through rich and returns the exit code: 0 done (check: every item passed), 1 a
failure (a FAIL row, a robot that moved: nothing stored), 2 bad input (one line, nothing sent on
the bus, nothing written), 130 Ctrl-C (every drive disabled first). The procedures are
:mod:`daror_runtime.commissioning`'s; modules are imported when a command runs (``daror --help``
stays fast).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rich.console import Console

from daror_runtime.cli.common import Commands, UsageError, bind, output_file, write_json

#: The drives' peak torque during a check, N m (0x6072): far below what could hurt (40 N m is the robot's).
DEFAULT_CHECK_TORQUE_LIMIT_NM = 2.0


def _config(args: argparse.Namespace) -> Any:
    """The robot file ``--hal-config`` as a HAL configuration (HalConfigError: one line)."""
    from hal.config import load_hal_config

    return load_hal_config(args.hal_config)


# --- scan ---------------------------------------------------------------------------------------


def cmd_can_scan(args: argparse.Namespace, console: Console) -> int:
    """Every node on the bus: id, NMT state, 0x1000, 0x1018, its EDS. Sends SDO reads only."""
    from rich.table import Table

    from hal.commissioning import scan

    if not (0 < args.listen_s <= 60):
        raise UsageError(f"--listen-s {args.listen_s:g}: expected a time above 0 s and at most 60 s")
    if args.json is not None:
        output_file(args.json)
    config = None
    if args.hal_config is not None:
        given = [f for f, v in (("--interface", args.interface), ("--channel", args.channel)) if v is not None]
        if given:
            raise UsageError(f"--hal-config names the bus; leave out {' and '.join(given)}")
        config = _config(args)
        if config.backend not in ("can", "can-sim"):
            raise UsageError(f"{args.hal_config}: backend {config.backend}; a scan needs backend can or can-sim")
        interface, channel, bitrate = config.interface, config.channel, config.bitrate
    elif args.interface is None or args.channel is None:
        raise UsageError("name the bus: --interface and --channel (and --bitrate), or --hal-config FILE")
    else:
        from hal.config import CAN_BITRATES

        if args.bitrate not in CAN_BITRATES:
            raise UsageError(
                f"--bitrate {args.bitrate}: expected one of the CiA 301 bit rates {', '.join(map(str, CAN_BITRATES))}"
            )
        interface, channel, bitrate = args.interface, args.channel, args.bitrate
    console.print(f"scanning {interface} {channel} at {bitrate} bit/s for {args.listen_s:g} s (SDO reads only) ...")
    result = scan(config, interface, channel, bitrate, args.listen_s, list(args.eds_dir or []))
    table = Table(title=f"nodes on {channel}")
    for column in ("node", "NMT state", "0x1000", "vendor", "product", "revision", "serial", "EDS"):
        table.add_column(column, overflow="fold")
    for node in result.nodes:
        values = [node.device_type, *(node.identity.get(sub) for sub in (1, 2, 3, 4))]
        shown = ["-" if v is None else f"0x{v:08X}" for v in values]
        eds = _relative(node.eds) if node.eds is not None else node.eds_note
        table.add_row(str(node.node_id), node.nmt_state, *shown, eds)
    console.print(table)
    for node in result.nodes:
        for problem in node.problems:
            console.print(f"  node {node.node_id}: {problem}", markup=False, soft_wrap=True)
    for problem in result.eds_problems:
        console.print(f"  EDS left out: {problem}", markup=False, soft_wrap=True)
    console.print(
        f"{len(result.nodes)} node(s) in {result.duration_s:.2f} s; {result.frames_sent} SDO read requests sent"
    )
    if args.json is not None:
        write_json(args.json, result.as_dict())
        console.print(f"{args.json}: written")
    return 0


def _relative(path: Path) -> str:
    """``path`` relative to the working folder when it is inside it (shorter in a table)."""
    try:
        return str(path.resolve().relative_to(Path.cwd()))
    except ValueError:
        return str(path)


# --- check --------------------------------------------------------------------------------------


def _session(config: Any, clock: str | None, torque_limit_nm: float) -> Any:
    """The backend (peak torque limited) and its clock: lock-step on hardware refused before the bus is touched."""
    from daror_runtime.commissioning.bus_session import BusSession, commissioning_backend, commissioning_clock

    hal = commissioning_backend(config, torque_limit_nm)
    return BusSession(hal, commissioning_clock(hal, clock))


def cmd_can_check(args: argparse.Namespace, console: Console) -> int:
    """Boot the bus, read every drive, enable each joint alone at zero torque; a table with PASS/FAIL per item."""
    from rich.table import Table

    from daror_runtime.commissioning.check import CheckLimits, run_check
    from daror_runtime.commissioning.expect import calibration_rows, expected_identity

    if args.json is not None:
        output_file(args.json)
    config = _config(args)
    session = _session(config, args.clock, args.torque_limit_nm)
    if session.hal.drives_hardware and not args.yes_no_pilot:
        raise UsageError(
            "daror can check enables each drive of the robot: nobody may sit in it. Confirm that nobody does, the "
            "arm links are free to move and the e-stops are in reach with --yes-no-pilot"
        )
    console.print(
        f"checking {len(config.node_ids)} drives on {config.interface} {config.channel} ({session.clock.name} clock, "
        f"peak torque {args.torque_limit_nm:g} N m) ..."
    )
    limits = CheckLimits(torque_limit_nm=args.torque_limit_nm)
    report = run_check(session, limits, expected_identity(config), calibration_rows=calibration_rows(args.hal_config))
    table = Table(title=f"daror can check {args.hal_config}")
    for column in ("joint", "node", "item", "found", "expected", ""):
        table.add_column(column, overflow="fold")
    colours = {"PASS": "green", "FAIL": "bold red", "INFO": "dim"}
    for row in report.rows:
        table.add_row(
            str(row.joint) if row.joint else "-", str(row.node_id) if row.node_id else "-", row.item, row.found,
            row.expected, f"[{colours[row.verdict]}]{row.verdict}[/]",
        )  # fmt: skip
    console.print(table)
    failed = sum(row.verdict == "FAIL" for row in report.rows)
    console.print(
        "every item passed; every drive disabled" if report.passed else f"{failed} item(s) FAILED", soft_wrap=True
    )
    if args.json is not None:
        write_json(args.json, report.as_dict())
        console.print(f"{args.json}: written")
    if report.interrupted:
        return 130
    return 0 if report.passed else 1


# --- zero and tare --------------------------------------------------------------------------------


def cmd_can_calibrate(args: argparse.Namespace, console: Console) -> int:
    """``daror can zero`` / ``daror can tare``: read every drive still and disabled, store the result per node."""
    from rich.table import Table

    from daror_runtime.commissioning.calibration import CalibrationLimits, measure_still, spread_problems, utc_now
    from daror_runtime.commissioning.robot_file import check_storable, read_calibrations, store_calibrations
    from hal.config import load_hal_config

    kind = args.can_command
    confirmed = args.at_zero_pose if kind == "zero" else args.arm_unloaded
    if not confirmed:
        flag, what = (
            ("--at-zero-pose", "the robot is in its zero pose (every joint at 0, the arm supported)")
            if kind == "zero"
            else ("--arm-unloaded", "the arm is unloaded (supported, or out of the robot)")
        )
        raise UsageError(f"daror can {kind} stores what the drives read now: confirm that {what} with {flag}")
    stored = read_calibrations(args.hal_config)  # a file without nodes: refused before the bus is touched
    config = _config(args)
    check_storable(args.hal_config, list(config.node_ids), verify=load_hal_config)  # before anything is measured
    session = _session(config, args.clock, DEFAULT_CHECK_TORQUE_LIMIT_NM)
    limits = CalibrationLimits()
    console.print(f"daror can {kind}: reading every drive for {limits.window_s:g} s, every drive disabled ...")
    readings, problems = measure_still(session, limits)
    problems += spread_problems(readings, kind, limits)
    now = utc_now()
    table = Table(title=f"daror can {kind}")
    columns = ("joint", "node", "motor counts", "link counts") if kind == "zero" else ("joint", "node", "spring N m")
    for column in (*columns, "stored before", "new"):
        table.add_column(column)
    updates: dict[int, dict[str, Any]] = {}
    for r in readings:
        before = stored.get(r.node_id, {})
        if kind == "zero":
            new = {"motor_zero_counts": round(r.motor_counts.mean), "link_zero_counts": round(r.link_counts.mean)}
            shown = (f"{r.motor_counts.mean:.1f} +- {r.motor_counts.spread:.1f}",
                     f"{r.link_counts.mean:.1f} +- {r.link_counts.spread:.1f}")  # fmt: skip
            old = f"{before.get('motor_zero_counts', '-')}, {before.get('link_zero_counts', '-')}"
            updates[r.node_id] = {**new, "zeroed_utc": now}
        else:
            # the backend reports the torque with the stored tare taken off: the new tare adds to it
            tare = round(float(before.get("torque_tare_nm", 0.0)) + r.spring_nm.mean, 4)
            new = {"torque_tare_nm": tare}
            shown = (f"{r.spring_nm.mean:+.4f} +- {r.spring_nm.spread:.4f}",)
            old = str(before.get("torque_tare_nm", "-"))
            updates[r.node_id] = {**new, "tared_utc": now}
        table.add_row(str(r.joint), str(r.node_id), *shown, old, ", ".join(str(v) for v in new.values()))
    console.print(table)
    if problems or not readings:
        for problem in problems or ["no reading"]:
            console.print(f"  {problem}", markup=False, soft_wrap=True)
        console.print(f"{args.hal_config}: not changed")
        return 1
    backup = store_calibrations(
        args.hal_config, updates, verify=load_hal_config, stamp=now.replace("-", "").replace(":", "")
    )
    console.print(f"{args.hal_config}: calibration of {len(updates)} nodes written ({kind}, {now}); previous: {backup}")
    return 0


# --- the parser -------------------------------------------------------------------------------------


def register(commands: Commands) -> None:
    """``daror can scan``, ``daror can check``, ``daror can zero`` and ``daror can tare`` on ``commands``."""
    can = commands.add_parser("can", help="commission a CAN bus: scan it, check the drives, zero and tare them")
    can_cmds = can.add_subparsers(dest="can_command", required=True, metavar="WHAT")

    scan = can_cmds.add_parser(
        "scan", help="every node on the bus: id, NMT state, 0x1000, 0x1018, its EDS (SDO reads only)"
    )
    scan.add_argument("--hal-config", type=Path, metavar="FILE", help="the robot file: its bus and its EDS folders")
    scan.add_argument("--interface", help="python-can interface (socketcan, pcan, virtual, ...)")
    scan.add_argument("--channel", help="python-can channel (can0, PCAN_USBBUS1, ...)")
    scan.add_argument("--bitrate", type=int, default=1_000_000, help="bit/s (default 1000000)")
    scan.add_argument(
        "--eds-dir", type=Path, action="append", metavar="DIR",
        help="a folder of EDS files to match nodes with (repeatable; default: the robot file's; the shipped one always)",
    )  # fmt: skip
    scan.add_argument("--listen-s", type=float, default=1.0, help="how long to listen for heartbeats, s (default 1)")
    scan.add_argument("--json", type=Path, metavar="FILE", help="write what was found as JSON here")
    bind(scan, cmd_can_scan)

    def bus_command(name: str, help: str) -> argparse.ArgumentParser:
        parser = can_cmds.add_parser(name, help=help)
        parser.add_argument("--hal-config", type=Path, metavar="FILE", required=True, help="the robot file")
        parser.add_argument(
            "--clock", choices=["realtime", "lockstep"],
            help="lockstep only on simulated drives (can-sim, the default there); realtime on the robot",
        )  # fmt: skip
        return parser

    check = bus_command("check", "boot the bus, read each drive, enable each joint alone at zero torque: PASS/FAIL")
    check.add_argument(
        "--yes-no-pilot", action="store_true",
        help="on the robot: confirm nobody sits in it, its links are free and the e-stops in reach (required)",
    )  # fmt: skip
    check.add_argument(
        "--torque-limit-nm", type=float, default=DEFAULT_CHECK_TORQUE_LIMIT_NM,
        help=f"the drives' peak torque during the check, N m (0x6072; default {DEFAULT_CHECK_TORQUE_LIMIT_NM:g})",
    )  # fmt: skip
    check.add_argument("--json", type=Path, metavar="FILE", help="write the table as JSON here")
    bind(check, cmd_can_check)

    zero = bus_command("zero", "store each drive's encoder counts at the robot's zero pose in the robot file")
    zero.add_argument(
        "--at-zero-pose", action="store_true", help="confirm the robot is in its zero pose, the arm supported"
    )
    bind(zero, cmd_can_calibrate)
    tare = bus_command("tare", "store each drive's spring torque with the arm unloaded in the robot file")
    tare.add_argument("--arm-unloaded", action="store_true", help="confirm the arm is unloaded (supported or out)")
    bind(tare, cmd_can_calibrate)
