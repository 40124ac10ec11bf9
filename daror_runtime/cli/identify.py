"""``daror identify``: the identification protocol run on the simulated plant (docs/identification.md)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import structlog
from rich.console import Console

from daror_runtime.cli.common import Commands, UsageError, bind, output_file, progress

log = structlog.get_logger(__name__)


def register(commands: Commands) -> None:
    """``daror identify`` on ``commands``."""
    ident = commands.add_parser("identify", help="run the identification protocol on the simulated plant")
    ident.add_argument("--scenario", required=True, help="scenario name (see 'daror simulate list') or a .yaml path")
    ident.add_argument("--trajectory", choices=["training", "validation"], help="the shipped protocol's run")
    ident.add_argument(
        "--protocol", type=Path, help="a designed protocol YAML (daror protocol design) instead of --trajectory"
    )
    ident.add_argument("--out", type=Path, required=True, help="stationary dataset to write (.csv, .npz, .mat)")
    ident.add_argument("--waypoints", type=Path, help="waypoint YAML (default: the shipped 83 waypoints)")
    ident.add_argument("--isb-limits", type=Path, help="the pilot's ISB limits YAML, enforced every tick")
    ident.add_argument("--feedforward", default="ap", help="gravity feed-forward: ap (default), none, or a MODEL.json")
    ident.add_argument("--dummy-arm", action="store_true", help="the Dummy Arm is installed (AP feed-forward)")
    ident.add_argument("--rate-hz", type=float, default=1000.0, help="loop rate (default 1000)")
    ident.add_argument(
        "--raw-format",
        choices=["npz", "csv", "mat"],
        default="npz",
        help="format of the raw log written beside --out (default npz: exact and fast; csv to read by eye)",
    )
    ident.add_argument(
        "--settings",
        type=Path,
        help="session settings YAML: its identification block (approach, settle, gains, points per stop) is used",
    )
    bind(ident, cmd_identify)


def cmd_identify(args: argparse.Namespace, console: Console) -> int:
    """Run the identification protocol (or a designed one) on the simulated plant, lock-step at ``--rate-hz``.

    Writes the stationary dataset ``--out``, the raw log beside it and their provenance; every
    input and output is checked before the plant runs (bad input: exit 2, nothing written).
    """
    from daror_runtime.data.load import raw_log_path, write_dataset
    from daror_runtime.data.provenance import simulated_pilot, simulated_robot, write_provenance
    from daror_runtime.identification.protocol import run_protocol
    from daror_runtime.models.files import load_model
    from daror_runtime.models.linear import APModel
    from daror_runtime.session.settings import load_session_settings
    from daror_runtime.util.outputs import output_lock
    from hal.config import hal_config
    from hal.interface import open_hal
    from hal.isb import load_isb_limits
    from hal.sim.scenario import load_scenario

    out = output_file(args.out)
    raw_path = output_file(raw_log_path(out, f".{args.raw_format}"))
    scenario = load_scenario(args.scenario)
    settings = load_session_settings(args.settings).identification
    _check_identify_run(args)
    isb = load_isb_limits(args.isb_limits) if args.isb_limits is not None else None
    hal = open_hal(hal_config("sim", "--scenario/--rate-hz", scenario=args.scenario, rate_hz=args.rate_hz))
    if args.feedforward == "ap":
        feedforward = APModel.from_description(hal.description, args.dummy_arm, args.dummy_arm)
    elif args.feedforward == "none":
        feedforward = None
    else:
        feedforward = load_model(args.feedforward)[0]
    trajectory, label, predicted_s = _identify_trajectory(args, settings.waypoints_file, isb, hal.description)
    log.info("identify requested", scenario=scenario.name, trajectory=label, out=str(out))
    # One writer per output: a second run naming the same --out is refused while this one runs. The
    # recording has a name of its own, so no run ever deletes another's (or a crashed run's) recording.
    with output_lock(out):
        recording = _unique_recording(out)
        hal.open()
        with progress(
            console,
            f"[bold]{label}[/bold] on {scenario.name}",
            "{task.completed:.0f}/{task.total:.0f} s robot time",
        ) as bar:
            task = bar.add_task("identify", total=trajectory.duration_s)
            result = run_protocol(
                hal,
                trajectory,
                recording,
                out,
                isb_limits=isb,
                settings=settings,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
                feedforward=feedforward,
            )
        hal.close()
        console.print(f"writing {out} and the raw log {raw_path} ...")
        write_dataset(out, result.stationary)
        write_dataset(raw_path, result.raw)
        for recorded in (out, raw_path):  # whose data: the simulated scenario's robot and pilot
            write_provenance(
                recorded, "identify", simulated_robot(hal.description.name, scenario.name),
                simulated_pilot(scenario.name), run=label, scenario=scenario.name,
            )  # fmt: skip
        recording.unlink(missing_ok=True)
    rms = " ".join(f"{v * 1e3:.1f}" for v in result.tracking_rms_rad)
    worst = " ".join(f"{v * 1e3:.1f}" for v in result.tracking_max_rad)
    console.print(f"{out}: {len(result.stationary)} stationary points from {result.stops} stops")
    console.print(f"{raw_path}: raw log, {len(result.raw)} samples at {args.rate_hz:g} Hz")
    console.print(f"  tracking error per joint, RMS {rms} mrad, worst {worst} mrad")
    console.print(
        f"  {result.robot_time_s:.0f} s of robot time in {result.wall_time_s:.1f} s "
        f"({result.real_time_factor:.0f}x real time, lock-step)"
    )
    if predicted_s is not None:
        console.print(
            f"  the protocol's predicted robot time: {predicted_s:.2f} s (measured {result.robot_time_s:.2f} s)"
        )
    # The process ends next: spare it the collections at exit over the ~120,000 objects numba keeps
    # (0.25 s of the command; the objects are freed as usual, only no longer traversed).
    import gc

    gc.freeze()
    return 0


def _check_identify_run(args: argparse.Namespace) -> None:
    """Exactly one of --trajectory and --protocol; --waypoints only with --trajectory."""
    if (args.trajectory is None) == (args.protocol is None):
        raise UsageError("expected --trajectory training|validation or --protocol PROTOCOL.yaml (one of them)")
    if args.protocol is not None and args.waypoints is not None:
        raise UsageError(
            "--waypoints: a designed protocol carries its own poses; leave --waypoints out with --protocol"
        )


def _identify_trajectory(
    args: argparse.Namespace, waypoints_file: Path | None, isb: Any, description: Any
) -> tuple[Any, str, float | None]:
    """The trajectory ``daror identify`` runs, its label, and a designed protocol's predicted robot time (s).

    A designed protocol is checked against ``--isb-limits`` when given, else against the limits it
    was designed in.
    """
    from daror_runtime.identification.protocol_file import load_protocol
    from daror_runtime.identification.trajectory_planning import build_trajectory, build_visit_trajectory
    from daror_runtime.identification.waypoints import load_waypoints
    from hal.isb import IsbLimits

    if args.protocol is None:
        waypoints = load_waypoints(args.waypoints or waypoints_file)
        trajectory = build_trajectory(waypoints, args.trajectory, limits=isb or IsbLimits(), description=description)
        return trajectory, args.trajectory, None
    protocol, visits = load_protocol(args.protocol)
    limits = isb or protocol.limits
    trajectory = build_visit_trajectory(
        visits, protocol.stops_s, protocol.trajectory_settings(), limits=limits, description=description
    )
    return trajectory, f"protocol {args.protocol.name}", protocol.prediction.robot_time_s


def _unique_recording(out: Path) -> Path:
    """A recording file for this run only (``.OUT.PID-XXXX.rec``); earlier runs' recordings are kept and named."""
    import os
    import tempfile

    earlier = sorted(out.parent.glob(f".{out.name}.*.rec"))
    if earlier:
        log.warning(
            "recordings of earlier runs that did not finish are kept",
            recordings=[str(p) for p in earlier],
            out=str(out),
        )
    fd, name = tempfile.mkstemp(prefix=f".{out.name}.{os.getpid()}-", suffix=".rec", dir=out.parent)
    os.close(fd)
    Path(name).unlink()  # the recorder creates it; the name is this run's
    return Path(name)
