"""``daror protocol design``: a short identification protocol designed for a pilot (issue 14; docs/identification.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.console import Console

from daror_runtime.cli.common import CommandParser, Commands, bind, non_negative_int, output_file, positive_int

#: The model ``--base`` designs for unless told.
_DEFAULT_BASE = "plf+"


def register(commands: Commands) -> None:
    """``daror protocol design`` on ``commands``; its flags declared when it is used (the design's registry imports scipy)."""
    protocol = commands.add_parser("protocol", help="short identification protocols designed for a pilot (issue 14)")
    protocol_cmds = protocol.add_subparsers(dest="protocol_command", required=True, metavar="WHAT")
    design = protocol_cmds.add_parser(
        "design", help="choose the poses that identify the model best within a budget of robot time (D-optimal)"
    )
    design.declare_on_use(_declare_design_flags)
    bind(design, cmd_protocol_design)


def _declare_design_flags(design: CommandParser) -> None:
    """The flags of ``daror protocol design``: the bases and the effects from the design model's registries."""
    from daror_runtime.identification.design_model import DESIGN_BASES, LINEAR_EFFECTS

    others = " or ".join(base for base in DESIGN_BASES if base != _DEFAULT_BASE)
    design.add_argument(
        "--budget-s", type=float, required=True, help="robot time of the whole run, approach included (s)"
    )
    design.add_argument("--limits", type=Path, metavar="ISB.yaml", help="the pilot's recorded ISB limits")
    design.add_argument(
        "--base", default=_DEFAULT_BASE, help=f"model to identify: {_DEFAULT_BASE} (default) or {others}"
    )
    design.add_argument(
        "--effects",
        metavar="E,E",
        help=f"linear effects of the augmented model on top: {', '.join(LINEAR_EFFECTS)} (optionally :JOINT)",
    )
    design.add_argument(
        "--approach",
        choices=["both", "once"],
        default="both",
        help="stop at every pose arriving from both directions (default; the direction error cancels) or once",
    )
    design.add_argument("--stop-s", type=float, default=1.0, help="stop at every data pose (s, default 1.0)")
    design.add_argument(
        "--direction-error-nm", type=_per_joint_nm, metavar="D1,D2,D3,D4",
        help="direction-dependent torque error per joint (default 0.25,0.75,0.35,0.15)",
    )  # fmt: skip
    design.add_argument(
        "--sensor-noise-nm", type=_per_joint_nm, metavar="S1,S2,S3,S4",
        help="torque noise of a stop per joint (default 0.024 each)",
    )  # fmt: skip
    design.add_argument("--candidates", type=positive_int, default=1024, help="candidate poses drawn (default 1024)")
    design.add_argument("--seed", type=non_negative_int, default=0, help="seed of the candidate poses (default 0)")
    design.add_argument("--robot", type=Path, help="robot description YAML (default: the packaged DAROR-01)")
    design.add_argument("--out", type=Path, required=True, metavar="PROTOCOL.yaml", help="protocol file to write")


def _per_joint_nm(text: str) -> tuple[float, float, float, float]:
    """A flag type: four torques of 0 Nm or more, joints 1-4 (argparse's one-line error otherwise)."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected four comma-separated torques in Nm") from None
    if len(values) != 4 or not all(v >= 0 and v < float("inf") for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: expected four torques of 0 Nm or more (joints 1-4)")
    return values[0], values[1], values[2], values[3]


def cmd_protocol_design(args: argparse.Namespace, console: Console) -> int:
    """Design a short identification protocol for a budget of robot time (docs/identification.md, section 8)."""
    from daror_runtime.identification.design import DesignSettings, design_protocol
    from daror_runtime.identification.design_model import parse_effects
    from daror_runtime.identification.protocol_file import write_protocol
    from daror_runtime.util.outputs import output_lock
    from hal.isb import IsbLimits, load_isb_limits
    from hal.robot import load_description

    out = output_file(args.out, args.limits)
    limits = load_isb_limits(args.limits) if args.limits is not None else IsbLimits()
    description = load_description(args.robot)
    defaults = DesignSettings()
    settings = DesignSettings(
        base=args.base.lower(),
        effects=parse_effects(args.effects),
        approach=args.approach,
        stop_s=args.stop_s,
        candidates=args.candidates,
        seed=args.seed,
        direction_error_nm=args.direction_error_nm or defaults.direction_error_nm,
        sensor_noise_nm=args.sensor_noise_nm or defaults.sensor_noise_nm,
    )
    result = design_protocol(args.budget_s, limits, description, settings)
    with output_lock(out):
        write_protocol(out, result.protocol)
    p = result.protocol.prediction
    console.print(f"{out}: {result.protocol.description}")
    console.print(
        f"  robot time {p.robot_time_s:.2f} s = approach {p.approach_s:.2f} + settle {p.settle_s:.2f} + moves "
        f"{p.moves_s:.2f} + stops {p.stops_s:.2f} s (budget {args.budget_s:g} s)"
    )
    console.print(
        f"  information matrix: log det {p.log_det:.2f}; condition number {p.condition_number:.3g} at unit diagonal, "
        f"{p.workspace_condition_number:.3g} relative to stops spread over the pilot's range"
    )
    joints = " ".join(f"{v:.3f}" for v in p.validation_rmse_per_joint_nm)
    console.print(f"  predicted validation RMSE {p.validation_rmse_nm:.4f} Nm (per joint {joints})")
    console.print("  predicted standard errors of the identifiable combinations:")
    for b in p.base_parameters:
        console.print(f"    {b.expression:60s} +- {b.std_error:.3g}")
    console.print(f"  designed from {result.candidates} candidate poses in {result.wall_s:.2f} s")
    return 0
