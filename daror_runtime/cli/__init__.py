"""The ``daror`` command (README.md; the file formats in docs/data.md and docs/residual.md).

Exit codes: 0 success, 1 failure, 2 bad input (a file, field or value a person handed in). Bad
input prints one line naming the file and the problem, and writes nothing.

One module per command group (:data:`COMMAND_MODULES`), each with a ``register(commands)`` that
adds its subcommands, their flags beside their handlers, and binds each handler
(:func:`daror_runtime.cli.common.bind`); :func:`main` runs the handler the parsed command is bound
to. What the commands share (the parser class, the top-level flags, exit codes, the HAL from
flags) is in :mod:`daror_runtime.cli.common`. Importing this package imports none of them: the
command modules are imported by :func:`build_parser`, and each imports its heavy modules when it
runs.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import argparse

__all__ = ["BLAS_THREAD_VARIABLES", "COMMAND_MODULES", "build_parser", "limit_blas_threads", "main"]

#: The command modules of :mod:`daror_runtime.cli`, in the order ``daror --help`` lists their commands.
COMMAND_MODULES = (
    "demo",  # demo
    "simulate",  # simulate static|list
    "identify",  # identify
    "models",  # fit, evaluate, cvf
    "residual",  # residual
    "study",  # study data-efficiency|protocol
    "data",  # data check
    "protocol",  # protocol design
    "hpsearch",  # hpsearch
    "console",  # console
    "hil",  # hil
    "fsm",  # fsm check|diagram|schema
    "bench",  # bench
    "rt_check",  # rt-check
    "can",  # can scan|check|zero|tare
    "records",  # pilots add|list|show, sessions list|add, db upgrade
)


def build_parser() -> argparse.ArgumentParser:
    """The ``daror`` parser: the top-level flags, then every command module's subcommands."""
    from daror_runtime.cli.common import CommandParser, add_common_flags

    parser = CommandParser(prog="daror", description="DAROR-01 control runtime and modelling tools")
    add_common_flags(parser)
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"{__name__}.{name}").register(commands)
    return parser


#: Thread-count variables of the BLAS libraries numpy and scipy may load.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def limit_blas_threads() -> None:
    """One BLAS thread for the command-line tools, unless the caller set a count.

    On a 2-core machine OpenBLAS's default of one thread per core fights any other load: a PLF+ fit
    of 25,000 samples took 224 ms (median; 29 ms quiet, with an outlier of 3.1 s) against 57 ms with
    one thread while the other core was busy (docs/performance.md). The variables are read when the
    libraries load, so this runs before any command imports numpy (the commands import lazily).
    """
    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``daror`` with ``argv`` (default: the process's arguments); returns the exit code.

    Bad flags exit through argparse (:class:`SystemExit` with code 2, one usage line and one error line).
    """
    limit_blas_threads()
    from daror_runtime.cli.common import make_console, run_command
    from daror_runtime.logs import configure_logging

    args = build_parser().parse_args(argv)
    configure_logging(args.log_level or "warning", args.log_json)
    return run_command(args, make_console())
