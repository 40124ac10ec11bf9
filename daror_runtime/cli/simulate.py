"""``daror simulate static|list``: simulated data without the control loop (docs/data.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

import structlog
from rich.console import Console

from daror_runtime.cli.common import Commands, bind, non_negative_int, output_file, positive_int

log = structlog.get_logger(__name__)


def register(commands: Commands) -> None:
    """``daror simulate static`` and ``daror simulate list`` on ``commands``."""
    sim = commands.add_parser("simulate", help="simulated data without the control loop")
    sim_cmds = sim.add_subparsers(dest="simulate_command", required=True, metavar="WHAT")
    static = sim_cmds.add_parser("static", help="a stationary dataset of a scenario (exo: dataset A, exo_dummy_arm: B)")
    static.add_argument("--scenario", required=True, help="scenario name (see 'daror simulate list') or a .yaml path")
    static.add_argument("--trajectory", choices=["training", "validation"], required=True)
    static.add_argument("--out", type=Path, required=True, help="output file (.csv, .npz or .mat)")
    static.add_argument("--waypoints", type=positive_int, default=83, help="waypoints in the workspace (default 83)")
    static.add_argument(
        "--sub-steps", type=non_negative_int, default=7, help="training stops between waypoints (default 7)"
    )
    static.add_argument("--samples-per-stop", type=positive_int, default=1, help="sensor readings per stop (default 1)")
    static.add_argument(
        "--noise-free", action="store_true", help="exact sensors: no noise, quantisation or direction error"
    )
    static.add_argument("--with-raw", action="store_true", help="also write a quasi-static raw log as FILE.raw.EXT")
    bind(static, cmd_simulate_static)
    listing = sim_cmds.add_parser("list", help="the shipped scenarios")
    bind(listing, cmd_simulate_list)


def cmd_simulate_static(args: argparse.Namespace, console: Console) -> int:
    """A stationary dataset of a scenario (and with ``--with-raw`` its quasi-static raw log) and its provenance."""
    from daror_runtime.data.load import raw_log_path, write_dataset
    from daror_runtime.data.provenance import simulated_pilot, simulated_robot, write_provenance
    from daror_runtime.data.schema import RawLog, StationaryDataset
    from hal.sim.quasi_static import QuasiStaticSettings, quasi_static_log
    from hal.sim.scenario import load_scenario
    from hal.sim.static_dataset import STREAM_RAW_LOG, generate_stationary, scenario_stops, stream

    output_file(args.out)
    if args.with_raw:
        output_file(raw_log_path(args.out))
    scenario = load_scenario(args.scenario)
    points = generate_stationary(
        scenario, args.trajectory, args.waypoints, args.sub_steps, args.samples_per_stop, args.noise_free
    )
    dataset = StationaryDataset(points.q_rad, points.tau_nm, points.direction, points.t_s)
    write_dataset(args.out, dataset)
    robot, pilot = simulated_robot(scenario.description().name, scenario.name), simulated_pilot(scenario.name)
    write_provenance(args.out, "simulate", robot, pilot, run=args.trajectory, scenario=scenario.name)
    log.info(
        "dataset written", path=str(args.out), scenario=scenario.name, trajectory=args.trajectory, points=len(dataset)
    )
    console.print(f"{args.out}: {len(dataset)} stationary points of scenario {scenario.name} ({args.trajectory})")
    if args.with_raw:
        stops = scenario_stops(scenario, args.trajectory, args.waypoints, args.sub_steps)
        raw = quasi_static_log(scenario, stops, stream(scenario.seed, STREAM_RAW_LOG), QuasiStaticSettings())
        raw_path = raw_log_path(args.out)
        write_dataset(raw_path, RawLog(raw.t_s, raw.q_rad, raw.dq_rad_s, raw.tau_nm, raw.theta_rad))
        write_provenance(raw_path, "simulate", robot, pilot, run=args.trajectory, scenario=scenario.name)
        console.print(f"{raw_path}: raw log, {len(raw.t_s)} samples")
    return 0


def cmd_simulate_list(args: argparse.Namespace, console: Console) -> int:
    """The shipped scenarios, one line each."""
    from hal.sim.scenario import load_scenario, scenario_names

    for name in scenario_names():
        console.print(f"{name:16s} {load_scenario(name).summary}")
    return 0
