"""``daror bench``: the benchmarks of docs/performance.md (:mod:`daror_runtime.bench`)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from daror_runtime.cli.common import Commands, bind, output_file
from daror_runtime.errors import DarorError


def register(commands: Commands) -> None:
    """``daror bench`` on ``commands``."""
    bench = commands.add_parser(
        "bench",
        help="run the benchmarks of docs/performance.md",
        add_help=False,  # its -h lists the benchmarks, loaded only then
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    bench.add_argument("-h", "--help", action=_BenchHelp, help="show this help and the benchmarks' names, and exit")
    bench.add_argument("--json", type=Path, help="write the figures as JSON here")
    bench.add_argument("--quick", action="store_true", help="fewer repetitions (a smoke run)")
    bench.add_argument("--only", help="run only benchmarks whose name contains this (see --list)")
    bench.add_argument("--list", action="store_true", help="list the benchmarks by script and exit")
    bind(bench, cmd_bench)


class _BenchHelp(argparse.Action):
    """``daror bench --help``: the usual help, then the benchmarks' names (their scripts are loaded only then)."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS, help: str | None = None) -> None:
        super().__init__(option_strings, dest=dest, default=argparse.SUPPRESS, nargs=0, help=help)

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
        from daror_runtime.bench import benchmark_list

        try:
            names = benchmark_list()
        except DarorError as exc:
            names = f"  {exc}"
        parser.epilog = f"benchmarks by script (--only runs those whose name contains its text):\n{names}"
        parser.print_help()
        parser.exit()


def cmd_bench(args: argparse.Namespace, console: Console) -> int:
    """Run the benchmarks (or list them with ``--list``); 0 when every benchmark ran, else 1."""
    from daror_runtime.bench import benchmark_list, run_benchmarks

    if args.list:
        console.print(
            f"benchmarks by script (--only runs those whose name contains its text):\n{benchmark_list()}",
            soft_wrap=True,
        )
        return 0
    if args.json is not None:
        output_file(args.json)
    return run_benchmarks(console, json_path=args.json, quick=args.quick, only=args.only)
