"""``daror demo``: the main job on the simulated plant, with a report (:mod:`daror_runtime.demo`)."""

from __future__ import annotations

import argparse

from rich.console import Console

from daror_runtime.cli.common import Commands, bind, output_dir


def register(commands: Commands) -> None:
    """``daror demo`` on ``commands``."""
    demo = commands.add_parser("demo", help="the main job on the simulated plant, with a report")
    demo.add_argument("--out", default="demo_out", help="directory for datasets, models and the report")
    bind(demo, cmd_demo)


def cmd_demo(args: argparse.Namespace, console: Console) -> int:
    """The main job on the simulated plant (:func:`daror_runtime.demo.run_demo`), its files and report in ``--out``."""
    from daror_runtime.demo import run_demo
    from daror_runtime.util.outputs import output_lock

    out = output_dir(args.out)
    with output_lock(out):
        run_demo(out, console)
    return 0
