"""``daror data check``: a dataset's signal map judged from physics (issue 27, docs/data.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.console import Console

from daror_runtime.cli.common import Commands, bind


def register(commands: Commands) -> None:
    """``daror data check`` on ``commands``."""
    data = commands.add_parser("data", help="datasets: check that their columns are what their names say")
    data_cmds = data.add_subparsers(dest="data_command", required=True, metavar="WHAT")
    check = data_cmds.add_parser(
        "check",
        help="judge a dataset's signal map from physics: the springs' torque, the command, the velocity, "
        "the A Priori torque; name the likely mix-up of its columns (exit 2 when the map looks wrong)",
    )
    check.add_argument("file", type=Path, help="a stationary dataset or a raw log (.csv, .npz, .mat, .parquet)")
    check.add_argument(
        "--dummy-arm",
        action="store_true",
        help="the Dummy Arm was installed: the A Priori torque of stationary points includes it",
    )
    bind(check, cmd_data_check)


def cmd_data_check(args: argparse.Namespace, console: Console) -> int:
    """Print every relation of ``args.file`` per joint; 0 when they all hold.

    Raises:
        DataError: the file cannot be read as a dataset (exit 2, one line).
        SignalMapError: a relation fails (after the report: exit 2, one line naming the joints,
            the relations and the likely mix-up).
    """
    from daror_runtime.data.load import load_dataset
    from daror_runtime.data.signal_map import SignalMapError, check_signal_map
    from hal.robot import load_description

    report = check_signal_map(load_dataset(args.file), load_description(), dummy_arm=args.dummy_arm)
    for line in report.lines():
        console.print(line, markup=False, highlight=False)
    if not report.passed:
        raise SignalMapError(report.failure_line())
    return 0
