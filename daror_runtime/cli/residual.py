"""``daror residual``: close the loop: the residual found, traced to physical effects, added, reported (docs/residual.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

import structlog
from rich.console import Console

from daror_runtime.cli.common import (
    TRUST_SIGNAL_MAP_HELP,
    CommandParser,
    Commands,
    UsageError,
    bind,
    output_dir,
    output_file,
)

log = structlog.get_logger(__name__)


def register(commands: Commands) -> None:
    """``daror residual`` on ``commands``; its flags declared when it is used (the effect families' registry imports numpy)."""
    residual = commands.add_parser(
        "residual", help="close the loop: find the residual, trace it to physical effects, add them, report"
    )
    residual.declare_on_use(_declare_flags)
    bind(residual, cmd_residual)


def _declare_flags(residual: CommandParser) -> None:
    """The flags of ``daror residual``: the base kinds from the model registry, the families from the effects'."""
    from daror_runtime.models.registry import kinds
    from daror_runtime.residual.effects import FAMILIES

    bases = [k.kind for k in kinds() if k.residual_base]
    residual.add_argument("--train", type=Path, required=True, help="training data (stationary dataset or raw log)")
    residual.add_argument("--validate", type=Path, required=True, help="validation data: every reported RMSE is on it")
    residual.add_argument("--trust-signal-map", action="store_true", help=TRUST_SIGNAL_MAP_HELP)
    residual.add_argument("--base", default="plf+", help=f"base model kind: {', '.join(bases)} (default plf+)")
    residual.add_argument(
        "--effects",
        help=f"comma-separated families to test (default all): {', '.join(FAMILIES)}; none: the base model alone",
    )
    residual.add_argument(
        "--raw",
        type=Path,
        nargs="+",
        metavar="FILE",
        help="the raw logs of the training (and validation) runs, the hysteresis's path (default: NAME.raw.* beside "
        "each dataset when there is one, else the points in order)",
    )
    dummy_arm_bases = " or ".join(k.kind for k in kinds() if k.residual_base and k.takes("dummy_arm"))
    residual.add_argument(
        "--dummy-arm", action="store_true", help=f"with --base {dummy_arm_bases}: add the Dummy Arm (Eq. 4.5, 4.7)"
    )
    residual.add_argument("--robot", type=Path, help="robot description (default: the packaged DAROR-01)")
    residual.add_argument(
        "--learned",
        action="store_true",
        help="last step (needs the extra nn): learn what the named effects leave with a PENN and an NNN, and say "
        "whether it is conservative; model_learned.json when it is",
    )
    residual.add_argument(
        "--out", type=Path, required=True, help="output folder: summary.json, report.md, plots, model.json"
    )


def _residual_base_takes_dummy_arm(base: str) -> None:
    """Refuse ``--dummy-arm`` with a base kind whose options have no Dummy Arm (an unknown base is refused later).

    Raises:
        UsageError: ``base`` is a kind the analysis augments but it takes no ``dummy_arm`` option.
    """
    from daror_runtime.models.registry import kind_names

    bases = kind_names(lambda entry: entry.residual_base)
    takers = kind_names(lambda entry: entry.residual_base and entry.takes("dummy_arm"))
    if base in bases and base not in takers:
        raise UsageError(
            f"--dummy-arm: the base model {base} takes no Dummy Arm (it learns it from the data); "
            f"only --base {' or '.join(takers)} does"
        )


def _raw_paths(raw: list[Path] | None) -> tuple[Path | None, Path | None] | None:
    """``--raw TRAIN [VALIDATE]`` as (training, validation) raw logs.

    Raises:
        UsageError: more than two files.
    """
    if raw is None:
        return None
    if len(raw) > 2:
        raise UsageError(
            f"--raw: {len(raw)} files; expected the training run's raw log and, optionally, the validation run's"
        )
    return raw[0], raw[1] if len(raw) == 2 else None


def cmd_residual(args: argparse.Namespace, console: Console) -> int:
    """Find the residual of the base model, trace it to physical effects, add them and report (in ``--out``).

    Raises:
        UsageError: unknown families, ``--dummy-arm`` with a base that takes none, more than two ``--raw``.
    """
    from rich.table import Table

    from daror_runtime.residual.pipeline import parse_families, run_residual
    from daror_runtime.residual.report import effect_rmse_nm, rmse_change
    from daror_runtime.util.outputs import output_lock
    from hal.robot import load_description

    families = parse_families(args.effects)
    if args.dummy_arm:
        _residual_base_takes_dummy_arm(args.base.lower())
    output_dir(args.out, args.train, args.validate)
    if args.out.is_dir():
        for name in ("summary.json", "model.json", "model_learned.json"):
            output_file(args.out / name, args.train, args.validate)
    description = load_description(args.robot)
    log.info("residual requested", train=str(args.train), validate=str(args.validate), base=args.base)
    with output_lock(args.out):
        run = run_residual(
            args.train,
            args.validate,
            args.out,
            description,
            args.base.lower(),
            families,
            dummy_arm=args.dummy_arm,
            learned=args.learned,
            raw_paths=_raw_paths(args.raw),
            trust_signal_map=args.trust_signal_map,
        )
    before, after = run.closure.before, run.closure.after
    table = Table(title=f"Validation errors, {args.base.upper()} before and after ({len(run.inputs.validate)} points)")
    for column in ("", "before (Nm)", "after (Nm)"):
        table.add_column(column, justify="right" if column else "left")
    for j in range(4):
        table.add_row(f"joint {j + 1}", f"{before.rmse_per_joint_nm[j]:.4f}", f"{after.rmse_per_joint_nm[j]:.4f}")
    table.add_row("RMSE", f"{before.rmse_nm:.4f}", f"{after.rmse_nm:.4f}")
    table.add_row("nRMSE", f"{before.nrmse:.4f}", f"{after.nrmse:.4f}")
    console.print(table)
    if not run.diagnosis.found:
        console.print("no effect found: nothing was added")
    for i, found in enumerate(run.diagnosis.found):
        rmse_before, rmse_after = effect_rmse_nm(run.closure, i)
        held = "" if rmse_after <= rmse_before else ": did not hold on the validation data"
        console.print(f"found: {found.sentence} ({rmse_change(rmse_before, rmse_after)}{held})")
    if run.travel is not None:
        chosen = "the hysteresis" if run.travel.hysteresis else "the direction offset"
        path = "the raw logs" if run.travel.from_raw_log else "the points in order (no raw log)"
        console.print(
            f"direction error: {chosen} (BIC {run.travel.bic_hysteresis:.0f} with the travel constants, "
            f"{run.travel.bic_direction:.0f} with the sign; the path from {path})"
        )
    for c in run.diagnosis.structured_correlates[:5]:
        console.print(f"unexplained: joint {c.joint} residual depends on {c.signal} (R^2 {c.r2:.2f})")
    for note in run.diagnosis.notes:
        console.print(f"note: {note}")
    if run.learned is not None:
        learned = run.learned
        table = Table(title="What remains, learned: validation RMSE (Nm)")
        for column in ("", "named effects", "+ PENN", "+ NNN"):
            table.add_column(column, justify="right" if column else "left")
        rows = [learned.named.rmse_per_joint_nm, learned.penn.rmse_per_joint_nm, learned.nnn.rmse_per_joint_nm]
        for j in range(4):
            table.add_row(f"joint {j + 1}", *(f"{r[j]:.4f}" for r in rows))
        table.add_row("RMSE", *(f"{m.rmse_nm:.4f}" for m in (learned.named, learned.penn, learned.nnn)))
        console.print(table)
        console.print(f"learned ({learned.verdict.replace('_', ' ')}): {learned.sentence}")
    written = "summary.json, report.md, model.json" + (
        ", model_learned.json" if "model_learned.json" in run.files else ""
    )
    console.print(f"{args.out}: {written}, diagnosis.json and plots written")
    log.info(
        "residual written",
        out=str(args.out),
        effects=[f.effect.label for f in run.diagnosis.found],
        rmse_before=before.rmse_nm,
        rmse_after=after.rmse_nm,
        unexplained=run.diagnosis.unexplained,
        learned=None if run.learned is None else run.learned.verdict,
    )
    return 0
