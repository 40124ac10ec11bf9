"""``daror study data-efficiency|protocol``: studies on recorded data (thesis Sec. 5.3; issue 14)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import structlog
from rich.console import Console

from daror_runtime.cli.common import (
    TRUST_SIGNAL_MAP_HELP,
    Commands,
    UsageError,
    bind,
    non_negative_int,
    output_dir,
    output_file,
    progress,
)

log = structlog.get_logger(__name__)


def register(commands: Commands) -> None:
    """``daror study data-efficiency`` and ``daror study protocol`` on ``commands``."""
    from daror_runtime.models.registry import kinds  # cheap: it imports no model code

    fitted = [k.kind for k in kinds() if k.needs_data]
    study = commands.add_parser("study", help="studies on recorded data (thesis Sec. 5.3)")
    study_cmds = study.add_subparsers(dest="study_command", required=True, metavar="WHAT")
    efficiency = study_cmds.add_parser(
        "data-efficiency", help="validation RMSE against the number of training points (Sec. 5.3.1, Fig. 5.4)"
    )
    efficiency.add_argument(
        "--train", type=Path, required=True, metavar="FILE", help="training set: stationary dataset or raw log"
    )
    efficiency.add_argument(
        "--validate", type=Path, required=True, metavar="FILE", help="validation set: stationary dataset or raw log"
    )
    efficiency.add_argument("--kind", default="plf+", help=f"fitted model kind: {', '.join(fitted)} (default plf+)")
    efficiency.add_argument("--trust-signal-map", action="store_true", help=TRUST_SIGNAL_MAP_HELP)
    efficiency.add_argument(
        "--sizes",
        metavar="N,N,...",
        help="comma-separated training-set sizes in points, 1..N (default: ~18 sizes, geometric, "
        "from the smallest identifiable size to all N points)",
    )
    efficiency.add_argument("--draws", type=int, default=100, help="random subsets (models) per size (default 100)")
    efficiency.add_argument("--seed", type=int, default=0, help="seed of the random subsets (default 0)")
    efficiency.add_argument(
        "--out", type=Path, required=True, metavar="DIR", help="directory for data_efficiency.json, .png and .md"
    )
    bind(efficiency, cmd_study_data_efficiency)
    pstudy = study_cmds.add_parser(
        "protocol",
        help="validation RMSE against robot time: designed protocols, random subsets, the full protocol (issue 14)",
    )
    pstudy.add_argument("--scenario", required=True, help="scenario name (see 'daror simulate list') or a .yaml path")
    pstudy.add_argument("--dummy-arm", action="store_true", help="the Dummy Arm is installed (AP feed-forward)")
    pstudy.add_argument(
        "--limits", type=Path, metavar="ISB.yaml", help="the pilot's ISB limits (default: the defaults)"
    )
    pstudy.add_argument("--budgets", metavar="S,S,...", help="robot-time budgets in s (default 45,60,90,120,180,240)")
    pstudy.add_argument(
        "--approaches", default="both,once", metavar="A,A", help="designs to run: both and/or once (default both,once)"
    )
    pstudy.add_argument("--draws", type=int, default=100, help="random subsets per budget and method (default 100)")
    pstudy.add_argument("--seed", type=non_negative_int, default=0, help="seed of the random subsets (default 0)")
    pstudy.add_argument(
        "--out", type=Path, required=True, metavar="DIR", help="directory for protocol_study.json, .png and .md"
    )
    bind(pstudy, cmd_study_protocol)


def cmd_study_data_efficiency(args: argparse.Namespace, console: Console) -> int:
    """Validation RMSE (Nm) against the number of training points (Sec. 5.3.1), written to ``--out``."""
    from daror_runtime.data.load import load_stationary_checked
    from daror_runtime.studies.data_efficiency import check_kind, parse_sizes, run_data_efficiency
    from daror_runtime.studies.data_efficiency_report import (
        output_paths,
        summary_table,
        write_outputs,
    )
    from daror_runtime.util.outputs import output_lock
    from hal.robot import load_description

    # Every cheap check before loading data or fitting: a refusal costs nothing and writes nothing.
    kind = check_kind(args.kind)
    sizes = parse_sizes(args.sizes) if args.sizes is not None else None
    output_dir(args.out, args.train, args.validate)
    for path in output_paths(args.out):
        if Path(args.out).is_dir():
            output_file(path, args.train, args.validate)
    description = load_description()
    train, train_map = load_stationary_checked(args.train, description, trust_signal_map=args.trust_signal_map)
    validate, validate_map = load_stationary_checked(args.validate, description, trust_signal_map=args.trust_signal_map)
    notes = tuple(note for note in (train_map.trust_note(), validate_map.trust_note()) if note is not None)
    log.info("data-efficiency study requested", kind=kind, train=str(args.train), validate=str(args.validate))
    with progress(console, f"[bold]{kind}[/bold] data efficiency", "{task.completed:.0f} fits") as bar:
        task = bar.add_task("study", total=None)
        result = run_data_efficiency(
            train,
            validate,
            description,
            kind=kind,
            sizes=sizes,
            draws=args.draws,
            seed=args.seed,
            progress=lambda done, total: bar.update(task, completed=done, total=total),
        )
    with output_lock(args.out):
        paths = write_outputs(result, args.out, notes)
    console.print(summary_table(result))
    console.print(f"  full-data fit ({result.train_points} points): validation RMSE {result.full_data_rmse:.4g} Nm")
    if result.enough_points is None:
        console.print(f"  no size studied has a mean RMSE within {result.tolerance:.0%} of the full-data RMSE")
    else:
        console.print(
            f"  enough points: {result.enough_points} ({result.enough_points / result.train_points:.1%} of the "
            f"training set): mean RMSE within {result.tolerance:.0%} of the full-data RMSE from there on"
        )
    console.print(f"  {sum(s.fitted + s.refused for s in result.sizes)} fits in {result.duration_s:.1f} s")
    for path in paths:
        console.print(f"{path}: written")
    return 0


def cmd_study_protocol(args: argparse.Namespace, console: Console) -> int:
    """Validation RMSE against robot time: designed protocols, random subsets, the full protocol."""
    from daror_runtime.models.linear import APModel
    from daror_runtime.studies.protocol_study import (
        DEFAULT_BUDGETS_S,
        parse_budgets,
        run_protocol_study,
    )
    from daror_runtime.studies.protocol_study_report import output_paths, summary_table, write_outputs
    from daror_runtime.util.outputs import output_lock
    from hal.config import hal_config
    from hal.interface import open_hal
    from hal.isb import IsbLimits, load_isb_limits
    from hal.sim.scenario import load_scenario

    budgets = parse_budgets(args.budgets) if args.budgets is not None else list(DEFAULT_BUDGETS_S)
    approaches = [a.strip() for a in args.approaches.split(",") if a.strip()]
    for approach in approaches:
        if approach not in ("both", "once"):
            raise UsageError(f"--approaches: {approach!r}; expected both and/or once, comma-separated")
    if args.draws < 1:
        raise UsageError(f"--draws {args.draws}: expected at least 1")
    output_dir(args.out, args.limits)
    if Path(args.out).is_dir():
        for path in output_paths(args.out):
            output_file(path, args.limits)
    scenario = load_scenario(args.scenario)
    limits = load_isb_limits(args.limits) if args.limits is not None else IsbLimits()

    def plant() -> Any:
        return open_hal(hal_config("sim", "--scenario", scenario=args.scenario))

    description = plant().description
    feedforward = APModel.from_description(description, args.dummy_arm, args.dummy_arm)
    with progress(console, f"[bold]protocol study[/bold] on {scenario.name}", "", elapsed=True) as bar:
        task = bar.add_task("study", total=None)
        result = run_protocol_study(
            scenario.name, plant, description, feedforward, args.dummy_arm, budgets, approaches, args.draws,
            args.seed, limits, progress=lambda what: bar.update(task, description=what),
        )  # fmt: skip
    with output_lock(args.out):
        paths = write_outputs(result, args.out)
    console.print(summary_table(result))
    console.print(f"  {result.wall_s:.0f} s of wall time")
    for path in paths:
        console.print(f"{path}: written")
    return 0
