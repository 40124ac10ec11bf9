"""``daror rt-check``: can this PC run the robot's loop at its rate? The real loop measured (docs/loop.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.console import Console

from daror_runtime.cli.common import (
    CommandParser,
    Commands,
    bind,
    hal_config_from_flags,
    hal_kinds,
    output_file,
    write_json,
)
from daror_runtime.logs import configure_logging


def register(commands: Commands) -> None:
    """``daror rt-check`` on ``commands``; its flags declared when it is used (``--hal``'s choices import the HAL)."""
    rt = commands.add_parser(
        "rt-check", help="can this PC run the robot's loop at its rate? the real loop measured (docs/loop.md)"
    )
    rt.declare_on_use(_declare_flags)
    bind(rt, cmd_rt_check, scenario=None)  # the plant is the backend's own: no --scenario


def _declare_flags(rt: CommandParser) -> None:
    """The flags of ``daror rt-check``; ``--hal``'s choices are the registered backends."""
    rt.add_argument("--seconds", type=float, default=30.0, help="how long to measure, s (default 30)")
    rt.add_argument("--hal", choices=hal_kinds(), help="the backend whose rate is checked (default sim)")
    rt.add_argument("--hal-config", type=Path, metavar="FILE", help="HAL configuration YAML: its backend's rate")
    rt.add_argument("--json", type=Path, metavar="FILE", help="write the report as JSON here")


def cmd_rt_check(args: argparse.Namespace, console: Console) -> int:
    """This PC's tick lateness with the real loop at the backend's rate: exit 0 if it can run the robot, 1 if not."""
    from daror_runtime.rt_check import check_seconds, measured_backend, run_rt_check

    check_seconds(args.seconds)
    if args.json is not None:
        output_file(args.json)
    backend, plant = measured_backend(hal_config_from_flags(args))
    # the watchdog's faults are what is measured: counted in the report, not logged on the terminal
    configure_logging(args.log_level or "critical", args.log_json)
    console.print(
        f"rt-check: the real loop at {plant.rate_hz:g} Hz (the {backend.kind} backend's rate) on the simulated "
        f"plant for {args.seconds:g} s ...",
        soft_wrap=True,
    )
    report = run_rt_check(backend, plant, args.seconds)
    f, late = report.figures, report.figures.lateness
    console.print(
        f"  {f.ticks} ticks on {report.deadlines} deadlines in {f.duration_s:.2f} s; lateness p50 {late.p50_us:.1f} us, "
        f"p99 {late.p99_us:.1f} us, p99.9 {late.p99_9_us:.1f} us, max {late.max_us:.1f} us",
        soft_wrap=True,
    )
    console.print(
        f"  {f.overruns} overruns, {f.missed_deadlines} missed deadlines, {f.watchdog_faults} overrun faults (the "
        f"watchdog: {f.overrun_limit} deadlines missed in a row, or a stall over {f.max_stall_periods} periods); "
        f"tick work {report.tick_work_mean_us:.0f} us mean, {report.tick_work_max_us:.0f} us worst",
        soft_wrap=True,
    )
    for refusal in report.refusals:
        console.print(f"  {refusal}", soft_wrap=True, markup=False)  # the OS's reason may hold brackets
    console.print(report.verdict.line, soft_wrap=True)
    if args.json is not None:
        write_json(args.json, report.as_dict())
        console.print(f"{args.json}: written")
    return 0 if report.verdict.can_run else 1
