"""The ``daror`` command (README.md; the file formats in docs/data.md and docs/residual.md).

Exit codes: 0 success, 1 failure, 2 bad input (a file, field or value a person handed in). Bad
input prints one line naming the file and the problem, and writes nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import structlog
from rich.console import Console

from daror_runtime.errors import DarorError, InputError, UsageError
from daror_runtime.logs import configure_logging

log = structlog.get_logger(__name__)

Handler = Callable[[argparse.Namespace, Console], int]


def _console() -> Console:
    return Console(highlight=False, width=120, soft_wrap=False)


def _write_json(path: Path | str, document: dict[str, Any]) -> None:
    from daror_runtime.util.atomic import write_text_atomic

    write_text_atomic(path, json.dumps(document, indent=2, allow_nan=False) + "\n")


def _at_least(minimum: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"{value} must be at least {minimum}")
        return value

    return parse


_positive_int = _at_least(1)
_non_negative_int = _at_least(0)


def _joint_angles(text: str) -> list[float]:
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected four comma-separated angles in radians") from None
    if len(values) != 4:
        raise argparse.ArgumentTypeError(f"{text!r}: expected four angles (q1,q2,q3,q4), got {len(values)}")
    return values


def _progress(console: Console, label: str, counter: str, elapsed: bool = False) -> Any:
    """A transient rich progress bar: ``label``, the bar, ``counter`` (a task format), time elapsed
    (with ``elapsed``), time left."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    shown = (TimeElapsedColumn(),) if elapsed else ()
    return Progress(
        TextColumn(label),
        BarColumn(),
        TextColumn(counter),
        *shown,
        TimeRemainingColumn(),
        console=console,
        transient=True,
    )


def _output_file(out: Path | str, *inputs: Path | str | None) -> Path:
    """Check an output file before any work (nothing is created); see :mod:`daror_runtime.util.outputs`."""
    from daror_runtime.util.outputs import check_output_file

    return check_output_file(out, *inputs)


def _output_dir(out: Path | str, *inputs: Path | str | None) -> Path:
    from daror_runtime.util.outputs import check_output_dir

    return check_output_dir(out, *inputs)


# --- simulate ---------------------------------------------------------------------------


def cmd_simulate_static(args: argparse.Namespace, console: Console) -> int:
    from daror_runtime.data.load import raw_log_path, write_dataset
    from daror_runtime.data.provenance import simulated_pilot, simulated_robot, write_provenance
    from daror_runtime.data.schema import RawLog, StationaryDataset
    from hal.sim.quasi_static import QuasiStaticSettings, quasi_static_log
    from hal.sim.scenario import load_scenario
    from hal.sim.static_dataset import STREAM_RAW_LOG, generate_stationary, scenario_stops, stream

    _output_file(args.out)
    if args.with_raw:
        _output_file(raw_log_path(args.out))
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
    from hal.sim.scenario import load_scenario, scenario_names

    for name in scenario_names():
        console.print(f"{name:16s} {load_scenario(name).summary}")
    return 0


# --- identify -----------------------------------------------------------------------------


def cmd_identify(args: argparse.Namespace, console: Console) -> int:

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

    out = _output_file(args.out)
    raw_path = _output_file(raw_log_path(out, f".{args.raw_format}"))
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
        with _progress(
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


# --- fit / evaluate / cvf ---------------------------------------------------------------


def _fit_options_given(args: argparse.Namespace) -> dict[str, Any]:
    """The model options given on the ``daror fit`` command line, by field name (flags left out are absent)."""
    from daror_runtime.models.registry import FIT_OPTION_FLAGS

    given = {field: getattr(args, field) for field in FIT_OPTION_FLAGS}
    return {field: value for field, value in given.items() if value is not None}


def cmd_fit(args: argparse.Namespace, console: Console) -> int:
    from daror_runtime.data.load import load_stationary
    from daror_runtime.models.files import save_model, training_summary
    from daror_runtime.models.registry import FIT_OPTION_FLAGS, fit_model, kind_entry, options_for
    from hal.robot import load_description

    kind = args.kind.lower()
    entry = kind_entry(kind)
    # the kind's own options: a flag it does not take is refused here, before any work
    options = options_for(kind, _fit_options_given(args), FIT_OPTION_FLAGS)
    if args.train is None and entry.needs_data:
        raise UsageError(f"model kind {kind} learns from data; give --train FILE")
    _output_file(args.out, args.train)
    description = load_description(args.robot)
    dataset = load_stationary(args.train) if args.train is not None else None
    log.info("fit requested", kind=kind, train=None if args.train is None else str(args.train))
    result = fit_model(kind, dataset, description, options)
    summary = training_summary(dataset, args.train) if dataset is not None else None
    save_model(args.out, result.model, summary, result.report)
    report = result.report
    log.info("model written", path=str(args.out), kind=kind, duration_s=round(report.duration_s, 6))
    console.print(f"{args.out}: {result.model.display_name} model {result.model.name!r} ({kind})")
    if report.training is not None:
        t = report.training
        console.print(
            f"  training: {t.n_points} points, RMSE {t.rmse_nm:.4g} Nm, nRMSE {t.nrmse:.4g}, per joint "
            + " ".join(f"{v:.3g}" for v in t.rmse_per_joint_nm)
        )
    if report.rank is not None:
        console.print(f"  regressor rank {report.rank} of {report.n_parameters} parameters; identifiable combinations:")
        for b in report.base_parameters:
            console.print(f"    {b.expression():58s} = {b.value:+.5g} +- {b.std_error:.2g}")
        if report.unidentifiable:
            console.print(f"  no effect on torque at all: {', '.join(report.unidentifiable)}")
    for note in report.notes:
        console.print(f"  {note}")
    return 0


def _load_models(paths: Sequence[Path]) -> tuple[list[Any], list[Any]]:
    """The models of ``paths`` and their files' training summaries; models of one name labelled apart by their paths."""
    from daror_runtime.models.compare import distinct_labels
    from daror_runtime.models.files import load_model

    loaded = [load_model(p) for p in paths]
    models = [model for model, _ in loaded]
    for model, label in zip(models, distinct_labels([m.name for m in models], paths), strict=True):
        model.name = label
    return models, [contents.training for _, contents in loaded]


def cmd_evaluate(args: argparse.Namespace, console: Console) -> int:
    from daror_runtime.data.load import load_stationary
    from daror_runtime.models.compare import evaluate_models, evaluation_document, evaluation_table

    if args.json is not None:
        _output_file(args.json, args.data, *args.models)
    from daror_runtime.residual.data import prediction_signal

    models, training = _load_models(args.models)
    data = load_stationary(args.data)
    signals = [prediction_signal(m, data, args.data) for m in models]
    evaluations = evaluate_models(models, data, signals, training)
    console.print(evaluation_table(evaluations, f"Errors on {args.data} ({len(data)} points), Eq. 4.31-4.32"))
    for e in evaluations:
        x = e.extrapolation
        if x is not None and x.n_outside and x.rmse_outside_nm is not None:
            inside = "none inside" if x.rmse_inside_nm is None else f"{x.rmse_inside_nm:.3g} Nm inside"
            console.print(
                f"{e.name}: {x.n_outside} of {x.n_points} points outside its training range, extrapolated: "
                f"RMSE {x.rmse_outside_nm:.3g} Nm there, {inside}"
            )
    if args.json is not None:
        _write_json(args.json, evaluation_document(evaluations))
        console.print(f"{args.json}: written")
    return 0


def cmd_cvf(args: argparse.Namespace, console: Console) -> int:
    from daror_runtime.models.compare import cvf_document, cvf_models, cvf_table
    from daror_runtime.models.cvf import THESIS_STEPS_RAD

    if args.json is not None:
        _output_file(args.json, *args.models)
    models, _ = _load_models(args.models)
    steps = THESIS_STEPS_RAD[: args.refinements + 1]
    evaluations = cvf_models(models, args.start, steps)
    console.print(cvf_table(evaluations))
    if args.json is not None:
        _write_json(args.json, cvf_document(evaluations))
        console.print(f"{args.json}: written")
    return 0 if all(e.result.conservative for e in evaluations) or not args.strict else 1


# --- residual ---------------------------------------------------------------------------


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
    from rich.table import Table

    from daror_runtime.residual.pipeline import parse_families, run_residual
    from daror_runtime.residual.report import effect_rmse_nm, rmse_change
    from daror_runtime.util.outputs import output_lock
    from hal.robot import load_description

    families = parse_families(args.effects)
    if args.dummy_arm:
        _residual_base_takes_dummy_arm(args.base.lower())
    _output_dir(args.out, args.train, args.validate)
    if args.out.is_dir():
        for name in ("summary.json", "model.json", "model_learned.json"):
            _output_file(args.out / name, args.train, args.validate)
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


# --- protocol ---------------------------------------------------------------------------


def _per_joint_nm(text: str) -> tuple[float, float, float, float]:
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

    out = _output_file(args.out, args.limits)
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


# --- study ----------------------------------------------------------------------------


def cmd_study_data_efficiency(args: argparse.Namespace, console: Console) -> int:

    from daror_runtime.data.load import load_stationary
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
    _output_dir(args.out, args.train, args.validate)
    for path in output_paths(args.out):
        if Path(args.out).is_dir():
            _output_file(path, args.train, args.validate)
    description = load_description()
    train = load_stationary(args.train)
    validate = load_stationary(args.validate)
    log.info("data-efficiency study requested", kind=kind, train=str(args.train), validate=str(args.validate))
    with _progress(console, f"[bold]{kind}[/bold] data efficiency", "{task.completed:.0f} fits") as bar:
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
        paths = write_outputs(result, args.out)
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
    _output_dir(args.out, args.limits)
    if Path(args.out).is_dir():
        for path in output_paths(args.out):
            _output_file(path, args.limits)
    scenario = load_scenario(args.scenario)
    limits = load_isb_limits(args.limits) if args.limits is not None else IsbLimits()

    def plant() -> Any:
        return open_hal(hal_config("sim", "--scenario", scenario=args.scenario))

    description = plant().description
    feedforward = APModel.from_description(description, args.dummy_arm, args.dummy_arm)
    with _progress(console, f"[bold]protocol study[/bold] on {scenario.name}", "", elapsed=True) as bar:
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


# --- hpsearch -----------------------------------------------------------------------------

#: The top-level modules of the optional extra ``nn`` that the search imports.
_NN_MODULES = ("jax", "jaxlib", "optax")


def cmd_hpsearch(args: argparse.Namespace, console: Console) -> int:
    """The hyper-parameter search of PENN and NNN (docs/hpsearch.md): every check first, then the run, then the files."""
    from daror_runtime.bench import machine
    from daror_runtime.data.load import load_stationary
    from daror_runtime.models.registry import ExtraNotInstalledError
    from daror_runtime.util.outputs import output_lock
    from hal.robot import load_description

    try:
        from daror_runtime.neural.hpsearch.executors import require_ray
        from daror_runtime.neural.hpsearch.grid import grid_from_argument
        from daror_runtime.neural.hpsearch.report import OUTPUT_NAMES, ranking, write_outputs
        from daror_runtime.neural.hpsearch.search import check_data, run_search
        from daror_runtime.neural.hpsearch.winner import fit_winners
        from daror_runtime.neural.hpsearch.work import default_cache_dir
    except ImportError as exc:
        if (exc.name or "").split(".")[0] not in _NN_MODULES:
            raise
        raise ExtraNotInstalledError(
            "the search trains networks with JAX and needs the optional extra 'nn', which is not installed: "
            f"pip install 'daror-runtime[nn]' ({exc})"
        ) from None
    grid = grid_from_argument(args.grid).with_loss(args.loss)
    if args.executor == "ray":
        require_ray()
        if args.ray_address is not None and args.workers is not None:
            raise UsageError("--workers: a Ray cluster (--ray-address) runs as many units at once as it has CPUs")
    elif args.ray_address is not None:
        raise UsageError("--ray-address goes with --executor ray")
    out = _output_dir(args.out, args.train)
    if out.is_dir() and any(out.iterdir()) and not args.force:
        raise UsageError(
            f"{out}: the folder is not empty; the search writes {', '.join(OUTPUT_NAMES)} there: "
            "choose another --out, or give --force to replace them"
        )
    if out.is_dir():
        for name in OUTPUT_NAMES:
            _output_file(out / name, args.train)
    data = load_stationary(args.train)
    check_data(grid, data)
    cache = args.cache_dir if args.cache_dir is not None else default_cache_dir()
    try:
        cache.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--cache-dir {cache}: cannot be used as a folder ({exc.strerror})") from None
    # the cores this process may run on (a shared machine or a container may give fewer than it has)
    workers = args.workers or (
        len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    )
    log.info(
        "hpsearch requested", grid=grid.name, networks=grid.n_networks, loss=grid.training.loss,
        executor=args.executor, workers=workers, train=str(args.train), out=str(out), cache=str(cache),
    )  # fmt: skip
    with output_lock(out):
        # the bar fills with the estimated work done (the expensive shapes run first), the counter
        # counts networks
        with _progress(
            console, f"[bold]hpsearch[/bold] {grid.name}", "{task.fields[networks]} networks", elapsed=True
        ) as bar:
            task = bar.add_task("hpsearch", total=1.0, networks=f"0/{grid.n_networks}")
            run = run_search(
                grid,
                data,
                executor=args.executor,
                workers=workers,
                ray_address=args.ray_address,
                cache_dir=cache,
                one_xla_thread=True,  # always: the same numbers whatever the number of workers
                on_progress=lambda done, total, work: bar.update(task, completed=work, networks=f"{done}/{total}"),
            )
        ranked = ranking(run.rows)
        best = {  # each model's first configuration, PENN first (the order of the files)
            model: next(c.best for c in ranked if c.best.model == model)
            for model in ("penn", "nnn")
            if model in grid.models
        }
        with console.status(f"fitting the best {' and '.join(m.upper() for m in best)} as daror fit does"):
            winners = fit_winners(best, grid, data, args.train, out, load_description(None))
        paths = write_outputs(run, out, machine(), winners)
    n = len(run.rows)
    console.print(
        f"{n} networks ({len(run.results)} shapes) in {run.wall_s:.1f} s, {n / run.wall_s:.2f} networks/s; "
        f"{grid.training.loss} loss"
    )
    for winner in winners:
        configs = [c for c in ranked if c.best.model == winner.model]
        row = winner.best
        console.print(
            f"  best {winner.model.upper()}: {row.layers} x {row.width} {row.activation}, {row.inputs} inputs, "
            f"lambda {row.l1:g}: MVL {row.mvl:.5g}, validation RMSE {row.val_rmse_nm:.4f} Nm; "
            f"{sum(c.best.collapsed for c in configs)} of {len(configs)} configurations collapsed"
        )
        written = f"{out / winner.file_name}" if winner.file_name is not None else f"no model file ({winner.problem})"
        console.print(f"    model: {written}; reproduce: {winner.command}", soft_wrap=True)
        for difference in winner.differences:
            console.print(f"    differs from the search: {difference}")
    console.print(f"{out}: {', '.join(p.name for p in paths)} written")
    log.info("hpsearch written", out=str(out), networks=n, wall_s=round(run.wall_s, 3))
    return 0


# --- demo / bench -----------------------------------------------------------------------


def cmd_demo(args: argparse.Namespace, console: Console) -> int:
    from daror_runtime.demo import run_demo
    from daror_runtime.util.outputs import output_lock

    out = _output_dir(args.out)
    with output_lock(out):
        run_demo(out, console)
    return 0


def cmd_bench(args: argparse.Namespace, console: Console) -> int:
    from daror_runtime.bench import benchmark_list, run_benchmarks

    if args.list:
        console.print(
            f"benchmarks by script (--only runs those whose name contains its text):\n{benchmark_list()}",
            soft_wrap=True,
        )
        return 0
    if args.json is not None:
        _output_file(args.json)
    return run_benchmarks(console, json_path=args.json, quick=args.quick, only=args.only)


def cmd_rt_check(args: argparse.Namespace, console: Console) -> int:
    """This PC's tick lateness with the real loop at the backend's rate: exit 0 if it can run the robot, 1 if not."""
    from daror_runtime.rt_check import check_seconds, measured_backend, run_rt_check

    check_seconds(args.seconds)
    if args.json is not None:
        _output_file(args.json)
    backend, plant = measured_backend(_hal_config(args))
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
        _write_json(args.json, report.as_dict())
        console.print(f"{args.json}: written")
    return 0 if report.verdict.can_run else 1


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


# --- console --------------------------------------------------------------------------


def _hal_config(args: argparse.Namespace) -> Any:
    """The HAL configuration of ``daror console``: ``--hal-config FILE``, or the ``--hal``/``--scenario`` flags.

    Raises:
        UsageError: ``--hal-config`` together with ``--hal`` or ``--scenario``; ``--scenario`` for ``--hal can``.
        HalConfigError: the file or the flags do not make a configuration (one line).
    """
    from hal.config import hal_config, load_hal_config

    if args.hal_config is not None:
        given = [flag for flag, value in (("--hal", args.hal), ("--scenario", args.scenario)) if value is not None]
        if given:
            raise UsageError(f"--hal-config names the backend and its scenario; leave out {' and '.join(given)}")
        return load_hal_config(args.hal_config)
    backend = args.hal or "sim"
    if args.scenario is not None and backend == "can":
        raise UsageError("--scenario names a simulated plant: it goes with --hal sim or can-sim, not --hal can")
    return hal_config(backend, source=f"--hal {backend}", scenario=args.scenario)


def cmd_console(args: argparse.Namespace, console: Console) -> int:
    from daror_runtime.clocks import session_clock
    from daror_runtime.console.commands import parse_context
    from daror_runtime.console.grammar import check_lines
    from daror_runtime.console.run import read_script, stdin_is_terminal
    from daror_runtime.fsm.spec import load_fsm_spec
    from daror_runtime.session.settings import load_session_settings
    from daror_runtime.util.outputs import output_lock
    from hal.interface import open_hal

    if args.web:  # without the web extra: one line saying how to install it, exit 2
        from daror_runtime.console.web import require_web_extra
        from daror_runtime.console.web.access import check_no_token

        require_web_extra()
        if args.no_token:  # a console without a token: the loopback only, refused before anything is written
            check_no_token(args.host)
    elif args.no_token:
        raise UsageError("--no-token goes with --web (the web console's token)")
    spec = load_fsm_spec(args.spec)  # a bad spec: the runtime refuses to start, nothing is written
    settings = load_session_settings(args.settings)
    hal = open_hal(_hal_config(args))  # a backend not built or not installed: one line, exit 2
    checked = None
    if args.script is not None:  # the whole script is checked before anything runs or is written
        checked = check_lines(
            read_script(args.script),
            str(args.script),
            parse_context(spec, hal.description, hal.world.fault_kinds if hal.world is not None else None),
        )
    typed = checked is None and stdin_is_terminal()
    if args.realtime and args.clock not in (None, "realtime"):
        raise UsageError(f"--realtime is --clock realtime; it contradicts --clock {args.clock}: give one of them")
    # paced or lock-step on hardware, lock-step typed or on the web: refused here, before anything is written
    clock = session_clock(hal, "realtime" if args.realtime else args.clock, live=typed or args.web)
    if args.out is None:  # the default: a new folder under ./sessions (created)
        _output_dir("sessions").mkdir(exist_ok=True)
    out = _output_dir(args.out if args.out is not None else Path("sessions") / time.strftime("%Y%m%d-%H%M%S"))
    with output_lock(out):  # one session per folder
        return _console_session(args, console, hal, out, spec, settings, checked, typed, clock)


def _console_session(
    args: argparse.Namespace,
    console: Console,
    hal: Any,
    out: Path,
    spec: Any,
    settings: Any,
    checked: Any,
    typed: bool,
    clock: Any,
    after_script: Callable[[Any, Any], None] | None = None,
) -> int:
    """The session itself, in ``out`` (checked and locked by :func:`cmd_console`), on ``clock``.

    ``after_script(runtime, session)`` runs when a script has ended or failed, before the session
    ends (``daror hil``: a fault's reaction under way plays out).

    Returns the exit code: the mode's (0, 1, 2), or 128 + the signal's number when SIGINT (Ctrl-C,
    130), SIGTERM (143) or SIGHUP (129) ended it, in any mode and state: torque off first, the
    reason named in the audit log and ``session.json`` (D124).
    """
    from daror_runtime.console.run import (
        announcing,
        history_path,
        make_session,
        run_interactive,
        run_piped,
        run_script,
        run_session,
    )
    from daror_runtime.runtime import Runtime

    realtime = not clock.virtual
    runtime = Runtime(hal, out, spec=spec, settings=settings, clock=clock)
    out.mkdir(parents=True, exist_ok=True)
    configure_logging(
        args.log_level or "critical",  # the console announces what the operator must see
        [out / "audit.jsonl", *([args.log_json] if args.log_json is not None else [])],  # the session keeps its own
    )
    runtime.open()
    web = None

    def body() -> tuple[int, str]:
        nonlocal web
        session = make_session(runtime, console)
        if getattr(args, "web", False):  # the browser and the terminal share the runtime and its log (not hil)
            from daror_runtime.console.web.serve import start_web

            web = start_web(runtime, session.world, args.host, args.port, require_token=not args.no_token)
            session.announcements = web.hub.terminal_reader()
            console.print(f"web console: {web.address}" + ("" if web.token else _NO_TOKEN_NOTE), soft_wrap=True)
        background = realtime and not typed  # the loop on its own thread: announcements printed as they come
        if background:
            runtime.start_background()
        with announcing(session, enabled=background):
            if checked is not None:
                try:
                    result = run_script(session, args.script, checked)
                except DarorError:
                    if after_script is not None:
                        after_script(runtime, session)
                    raise
                if after_script is not None:
                    after_script(runtime, session)
                console.print(f"script done: {result.lines_run} lines, state {result.state}")
                return 0, "quit" if result.quit else "the script ended"
            if typed:
                run_interactive(session, history_path(), start=runtime.start_background)
                return 0, "quit"
            if web is None:
                return run_piped(session, sys.stdin), "quit or the end of the input"
            # the page is the console: until a signal, or until the server is lost (nothing would control the robot)
            reason = web.serve_until_interrupted()
            console.print(f"web console: {reason}", soft_wrap=True)
            return 0, reason

    def stop_web() -> None:
        if web is not None:
            web.stop()

    return run_session(runtime, console, body, stop_web)  # SIGINT, SIGTERM, SIGHUP: torque off, 128 + signal


#: Said after the web console's address when it asks no token (``--no-token``, loopback only).
_NO_TOKEN_NOTE = " (no token: any program on this computer can drive the robot)"


# --- hil ------------------------------------------------------------------------------

#: ``--fault KIND:NODE@T_S``: a drive's fault, its node id, the robot time it happens at; ``--fault KIND@T_S``:
#: a fault of the bus itself (the master's controller: bus_off, error_passive).
_FAULT_RE = re.compile(r"^(?P<kind>[a-z_]+)(?::(?P<node>\d{1,3}))?@(?P<at>[0-9]+(?:\.[0-9]*)?)$")


def _parse_fault(
    text: str, node_ids: list[int], kinds: tuple[str, ...], bus_kinds: tuple[str, ...] = ()
) -> tuple[str, int, float]:
    """``(kind, joint 1-4, robot time s)`` of one ``--fault KIND:NODE@T_S``; joint 0 for ``--fault BUS_KIND@T_S``.

    Raises:
        UsageError: not of that form, an unknown kind, a node that is not one of the drives', a
            drive's fault without a node or a bus fault with one.
    """
    match = _FAULT_RE.match(text)
    if match is None:
        raise UsageError(
            f"--fault {text!r}: expected KIND:NODE@T_S or a bus fault KIND@T_S, e.g. heartbeat_loss:2@30.5"
        )
    kind, at = match["kind"], float(match["at"])
    if kind not in kinds and kind not in bus_kinds:
        raise UsageError(f"--fault {text!r}: unknown fault {kind!r}; expected one of {', '.join((*kinds, *bus_kinds))}")
    if kind in bus_kinds:
        if match["node"] is not None:
            raise UsageError(f"--fault {text!r}: {kind} is a fault of the bus, not of a node: expected {kind}@T_S")
        return kind, 0, at
    if match["node"] is None:
        raise UsageError(f"--fault {text!r}: {kind} is a drive's fault: expected {kind}:NODE@T_S")
    node = int(match["node"])
    if node not in node_ids:
        raise UsageError(f"--fault {text!r}: node {node} is not a drive; expected one of {node_ids}")
    return kind, node_ids.index(node) + 1, at


def cmd_hil(args: argparse.Namespace, console: Console) -> int:
    """A console script over simulated CANopen drives, lock-step: the session, the audit log and the bus log.

    Once the run has started, its files are written whatever the session or the script did:
    ``hil.json`` says which faults were injected, when, and how the robot reacted
    (:mod:`daror_runtime.hil`), and a failed script still exits 1 after it.
    """
    from daror_runtime.clocks import LockStepClock
    from daror_runtime.console.commands import parse_context
    from daror_runtime.console.grammar import check_lines
    from daror_runtime.console.run import read_script
    from daror_runtime.fsm.spec import load_fsm_spec
    from daror_runtime.hil import (
        ScheduledFault,
        fault_lines,
        fault_summaries,
        hil_config,
        let_the_reaction_play_out,
        read_audit,
    )
    from daror_runtime.session.settings import load_session_settings
    from daror_runtime.util.atomic import write_text_atomic
    from daror_runtime.util.outputs import output_lock
    from hal.capabilities import BUS_FAULT_KINDS, BUS_LINE_FAULT_KINDS, BusStatistics, FaultSchedule
    from hal.interface import open_hal

    spec = load_fsm_spec(args.spec)
    settings = load_session_settings(args.settings)
    out = _output_dir(args.out, args.script)
    traffic = out / "can.log.gz"  # compressed as it is written (D137): zcat can.log.gz | canplayer
    for name in (traffic, out / "can.log", out / "hil.json"):
        if name.exists():
            raise UsageError(f"{name}: exists; a HIL run writes a new one: expected another --out")
    config = hil_config(args.hal_config, args.scenario, args.rate_hz, traffic)
    faults = [
        _parse_fault(text, list(config.node_ids), BUS_FAULT_KINDS, BUS_LINE_FAULT_KINDS) for text in args.fault or []
    ]
    hal = open_hal(config)
    world = hal.world
    if not isinstance(world, FaultSchedule) or not isinstance(hal, BusStatistics):
        raise UsageError(f"the {config.backend} backend schedules no faults")  # the registry was changed
    checked = check_lines(
        read_script(args.script), str(args.script), parse_context(spec, hal.description, world.fault_kinds)
    )
    for kind, joint, at_s in faults:
        world.schedule_fault(kind, joint, at_s)
    clock = LockStepClock(1.0 / hal.rate_hz)
    scheduled = [ScheduledFault(k, config.node_ids[j - 1] if j else None, j, t) for k, j, t in faults]
    with output_lock(out):
        code, error = 1, None
        try:
            code = _console_session(
                args, console, hal, out, spec, settings, checked, False, clock,
                after_script=lambda runtime, session: let_the_reaction_play_out(
                    runtime, session.say, session.show_announcements
                ),
            )  # fmt: skip
        except DarorError as exc:  # a failed script or session: its files are written all the same, then exit 1
            code, error = (2 if isinstance(exc, InputError) else 1), str(exc)
            raise
        finally:  # the session is closed (torque off, session.json, the bus log): what it did, in hil.json
            audit_path = out / "audit.jsonl"  # the session's own; else where --log-json sent its lines
            audit = read_audit(audit_path if audit_path.exists() or args.log_json is None else args.log_json)
            summaries = fault_summaries(
                scheduled, world.drive_events(), audit, spec, list(config.node_ids), hal.rate_hz
            )
            report = {
                "script": str(args.script),
                "exit_code": code,
                "error": error,
                "faults": summaries,
                "bus": hal.bus_report(),
            }
            write_text_atomic(out / "hil.json", json.dumps(report, indent=2, default=str) + "\n")
            for line in fault_lines(summaries):
                console.print(line, soft_wrap=True)
            frames = report["bus"].get("frames_sent", 0)  # type: ignore[union-attr]
            console.print(f"hil.json: {out / 'hil.json'}; bus log: {traffic} ({frames} frames sent)")
    return code


# --- fsm ------------------------------------------------------------------------------


def cmd_fsm_check(args: argparse.Namespace, console: Console) -> int:
    from rich.table import Table

    from daror_runtime.fsm.machine import Event, transition_table
    from daror_runtime.fsm.spec import DEFAULT_SPEC_PATH, load_fsm_spec

    path = args.spec or DEFAULT_SPEC_PATH
    spec = load_fsm_spec(path)
    console.print(
        f"{path}: valid ({len(spec.states)} states in {len(spec.superstates)} superstates, and {spec.fail.name})"
    )
    states = Table(title="states")
    for column in ("#", "superstate", "state", "mode", "torque Nm", "speed rad/s", "fault enters FAIL", "ISB limits"):
        states.add_column(column, overflow="fold", no_wrap=column in ("state", "mode"))
    for s in spec.states:
        states.add_row(
            str(s.number), s.superstate, s.name, s.mode, f"{s.limits.torque_nm:g}", f"{s.limits.velocity_rad_s:g}",
            "yes" if s.fail_on_fault else "no (e-stop test)", "yes" if s.enforce_isb else "no",
        )  # fmt: skip
    states.add_row("F", "-", spec.fail.name, spec.fail.mode, "0", "-", "-", "-")
    console.print(states)
    transitions = Table(title="transitions (every guard must hold; advance also needs the operator's press)")
    for column in ("from", "event", "to", "guards"):
        transitions.add_column(column)
    for (source, event), t in transition_table(spec).items():
        dest = "(stays)" if event == Event.ACKNOWLEDGE else t.dest
        transitions.add_row(source, event.value, dest, ", ".join(t.guards) or "-")
    console.print(transitions)
    return 0


def cmd_fsm_diagram(args: argparse.Namespace, console: Console) -> int:
    from daror_runtime.fsm.diagram import mermaid
    from daror_runtime.fsm.spec import load_fsm_spec

    return _emit(mermaid(load_fsm_spec(args.spec)), args.out, console)


def cmd_fsm_schema(args: argparse.Namespace, console: Console) -> int:
    from daror_runtime.fsm.spec import spec_json_schema_text

    return _emit(spec_json_schema_text(), args.out, console)


def _emit(text: str, out: Path | None, console: Console) -> int:
    """``text`` to standard output, or atomically to ``out``."""
    from daror_runtime.util.atomic import write_text_atomic

    if out is None:
        sys.stdout.write(text)
    else:
        write_text_atomic(_output_file(out), text)
        console.print(f"wrote {out}")
    return 0


# --- parser -----------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="daror", description="DAROR-01 control runtime and modelling tools")
    parser.add_argument(
        "--log-level",
        default=None,
        choices=["debug", "info", "warning", "error"],
        help="least severe event shown on stderr (default warning; the console shows its own announcements)",
    )
    parser.add_argument("--log-json", type=Path, help="also append every event from info up as JSON lines to this file")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    demo = commands.add_parser("demo", help="the main job on the simulated plant, with a report")
    demo.add_argument("--out", default="demo_out", help="directory for datasets, models and the report")
    demo.set_defaults(handler=cmd_demo)

    sim = commands.add_parser("simulate", help="simulated data without the control loop")
    sim_cmds = sim.add_subparsers(dest="simulate_command", required=True, metavar="WHAT")
    static = sim_cmds.add_parser("static", help="a stationary dataset of a scenario (exo: dataset A, exo_dummy_arm: B)")
    static.add_argument("--scenario", required=True, help="scenario name (see 'daror simulate list') or a .yaml path")
    static.add_argument("--trajectory", choices=["training", "validation"], required=True)
    static.add_argument("--out", type=Path, required=True, help="output file (.csv, .npz or .mat)")
    static.add_argument("--waypoints", type=_positive_int, default=83, help="waypoints in the workspace (default 83)")
    static.add_argument(
        "--sub-steps", type=_non_negative_int, default=7, help="training stops between waypoints (default 7)"
    )
    static.add_argument(
        "--samples-per-stop", type=_positive_int, default=1, help="sensor readings per stop (default 1)"
    )
    static.add_argument(
        "--noise-free", action="store_true", help="exact sensors: no noise, quantisation or direction error"
    )
    static.add_argument("--with-raw", action="store_true", help="also write a quasi-static raw log as FILE.raw.EXT")
    static.set_defaults(handler=cmd_simulate_static)
    listing = sim_cmds.add_parser("list", help="the shipped scenarios")
    listing.set_defaults(handler=cmd_simulate_list)

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
    ident.set_defaults(handler=cmd_identify)

    # Every list of model kinds below comes from the model registry (cheap: it imports no model code).
    from daror_runtime.models.registry import kinds

    every_kind = kinds()
    without_data = [k.kind for k in every_kind if not k.needs_data]
    fitted = [k.kind for k in every_kind if k.needs_data]
    bases = [k.kind for k in every_kind if k.residual_base]

    def taken_by(option: str) -> str:
        return ", ".join(k.kind for k in every_kind if k.takes(option)) or "no registered kind"

    fit = commands.add_parser(
        "fit",
        help=f"fit a compensation model: {', '.join(k.kind for k in every_kind)}",
        epilog="model kinds:\n" + "\n".join(f"  {k.kind:10s} {k.summary}" for k in every_kind),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    fit.add_argument("kind", help=f"model kind: {', '.join(k.kind for k in every_kind)} (see the list below)")
    fit.add_argument(
        "--train", type=Path, help=f"stationary dataset or raw log (optional for {', '.join(without_data)})"
    )
    fit.add_argument("--out", type=Path, required=True, help="model file to write (JSON)")
    fit.add_argument("--name", help="model name shown in tables (default: the kind's name)")
    fit.add_argument("--robot", type=Path, help="robot description YAML (default: the packaged DAROR-01)")
    fit.add_argument(
        "--dummy-arm",
        action="store_true",
        default=None,
        help=f"{taken_by('dummy_arm')}: include the Dummy Arm (Eq. 4.5)",
    )
    stiff = fit.add_mutually_exclusive_group()
    stiff.add_argument(
        "--elbow-stiffness",
        dest="elbow_stiffness",
        action="store_true",
        default=None,
        help=f"{taken_by('elbow_stiffness')}: include the first-order elbow stiffness (Eq. 4.7); default with --dummy-arm",
    )
    stiff.add_argument("--no-elbow-stiffness", dest="elbow_stiffness", action="store_false")
    fit.add_argument(
        "--seed", type=int, default=None, help=f"random seed of the models that use one ({taken_by('seed')})"
    )
    # The neural kinds' options (daror_runtime.neural.presets): each replaces one field of the preset.
    # Values are checked by the kind's options model, so a kind that does not take one refuses it.
    nets = taken_by("layers")
    fit.add_argument(
        "--thesis",
        action="store_true",
        default=None,
        help=f"{taken_by('thesis')}: the thesis's network and loss (Tables I, II; Eq. 3.7) instead of the default",
    )
    fit.add_argument("--layers", type=int, default=None, metavar="N", help=f"{nets}: hidden layers (1-32)")
    fit.add_argument("--width", type=int, default=None, metavar="N", help=f"{nets}: units per hidden layer (1-256)")
    fit.add_argument("--activation", default=None, metavar="A", help=f"{nets}: tanh, sigmoid, relu or softplus")
    fit.add_argument("--inputs", default=None, metavar="q|sincos", help=f"{nets}: q, or [sin q, cos q] (Eq. 4.28)")
    fit.add_argument("--l1", type=float, default=None, metavar="X", help=f"{taken_by('l1')}: L1 rate lambda")
    fit.add_argument(
        "--inits", type=int, default=None, metavar="N", help=f"{taken_by('inits')}: initialisations (best MVL kept)"
    )
    fit.add_argument("--folds", type=int, default=None, metavar="K", help=f"{taken_by('folds')}: validation blocks")
    fit.add_argument(
        "--adam-steps", dest="adam_steps", type=int, default=None, metavar="N", help=f"{nets}: full-batch Adam steps"
    )
    lbfgs = fit.add_mutually_exclusive_group()
    lbfgs.add_argument(
        "--lbfgs", dest="lbfgs", action="store_true", default=None, help=f"{taken_by('lbfgs')}: finish with L-BFGS"
    )
    lbfgs.add_argument("--no-lbfgs", dest="lbfgs", action="store_false")
    fit.add_argument(
        "--base",
        default=None,
        metavar="KIND",
        help=f"{taken_by('base')}: the physical model fitted first "
        f"({', '.join(k.kind for k in every_kind if k.physical)}; default plf+)",
    )
    fit.set_defaults(handler=cmd_fit)

    ev = commands.add_parser("evaluate", help="RMSE and nRMSE of models on a dataset (Table III)")
    ev.add_argument("models", type=Path, nargs="+", metavar="MODEL.json")
    ev.add_argument("--data", type=Path, required=True, help="stationary dataset or raw log")
    ev.add_argument("--json", type=Path, help="write the figures as JSON here")
    ev.set_defaults(handler=cmd_evaluate)

    cvf = commands.add_parser("cvf", help="closed-path energy test: is the model conservative? (Table IV)")
    cvf.add_argument("models", type=Path, nargs="+", metavar="MODEL.json")
    cvf.add_argument("--json", type=Path, help="write the figures as JSON here")
    cvf.add_argument("--start", type=_joint_angles, help="start q1,q2,q3,q4 in rad (default: centre of the range)")
    cvf.add_argument(
        "--refinements",
        type=int,
        choices=[1, 2],
        default=2,
        help="tenfold step refinements after pi/400 (default 2: down to pi/40000)",
    )
    cvf.add_argument("--strict", action="store_true", help="exit 1 when a model is not conservative")
    cvf.set_defaults(handler=cmd_cvf)

    residual = commands.add_parser(
        "residual", help="close the loop: find the residual, trace it to physical effects, add them, report"
    )
    residual.add_argument("--train", type=Path, required=True, help="training data (stationary dataset or raw log)")
    residual.add_argument("--validate", type=Path, required=True, help="validation data: every reported RMSE is on it")
    residual.add_argument("--base", default="plf+", help=f"base model kind: {', '.join(bases)} (default plf+)")
    residual.add_argument(
        "--effects",
        help="comma-separated families to test (default all): direction_offset, hysteresis, joint_stiffness, "
        "gravity_tilt, encoder_offset, torque_gain; none: the base model alone",
    )
    residual.add_argument(
        "--raw",
        type=Path,
        nargs="+",
        metavar="FILE",
        help="the raw logs of the training (and validation) runs, the hysteresis's path (default: NAME.raw.* beside "
        "each dataset when there is one, else the points in order)",
    )
    dummy_arm_bases = " or ".join(k.kind for k in every_kind if k.residual_base and k.takes("dummy_arm"))
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
    residual.set_defaults(handler=cmd_residual)

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
    efficiency.set_defaults(handler=cmd_study_data_efficiency)
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
    pstudy.add_argument("--seed", type=_non_negative_int, default=0, help="seed of the random subsets (default 0)")
    pstudy.add_argument(
        "--out", type=Path, required=True, metavar="DIR", help="directory for protocol_study.json, .png and .md"
    )
    pstudy.set_defaults(handler=cmd_study_protocol)

    protocol = commands.add_parser("protocol", help="short identification protocols designed for a pilot (issue 14)")
    protocol_cmds = protocol.add_subparsers(dest="protocol_command", required=True, metavar="WHAT")
    pdesign = protocol_cmds.add_parser(
        "design", help="choose the poses that identify the model best within a budget of robot time (D-optimal)"
    )
    pdesign.add_argument(
        "--budget-s", type=float, required=True, help="robot time of the whole run, approach included (s)"
    )
    pdesign.add_argument("--limits", type=Path, metavar="ISB.yaml", help="the pilot's recorded ISB limits")
    pdesign.add_argument("--base", default="plf+", help="model to identify: plf+ (default) or plf")
    pdesign.add_argument(
        "--effects",
        metavar="E,E",
        help="linear effects of the augmented model on top: direction_offset, joint_stiffness (optionally :JOINT)",
    )
    pdesign.add_argument(
        "--approach",
        choices=["both", "once"],
        default="both",
        help="stop at every pose arriving from both directions (default; the direction error cancels) or once",
    )
    pdesign.add_argument("--stop-s", type=float, default=1.0, help="stop at every data pose (s, default 1.0)")
    pdesign.add_argument(
        "--direction-error-nm", type=_per_joint_nm, metavar="D1,D2,D3,D4",
        help="direction-dependent torque error per joint (default 0.25,0.75,0.35,0.15)",
    )  # fmt: skip
    pdesign.add_argument(
        "--sensor-noise-nm", type=_per_joint_nm, metavar="S1,S2,S3,S4",
        help="torque noise of a stop per joint (default 0.024 each)",
    )  # fmt: skip
    pdesign.add_argument("--candidates", type=_positive_int, default=1024, help="candidate poses drawn (default 1024)")
    pdesign.add_argument("--seed", type=_non_negative_int, default=0, help="seed of the candidate poses (default 0)")
    pdesign.add_argument("--robot", type=Path, help="robot description YAML (default: the packaged DAROR-01)")
    pdesign.add_argument("--out", type=Path, required=True, metavar="PROTOCOL.yaml", help="protocol file to write")
    pdesign.set_defaults(handler=cmd_protocol_design)

    hp = commands.add_parser(
        "hpsearch", help="hyper-parameter search of PENN and NNN: Tables I and II (thesis Sec. 4.2.5)"
    )
    hp.add_argument(
        "--train", type=Path, required=True, metavar="FILE", help="training data: stationary dataset or raw log"
    )
    hp.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="DIR",
        help="folder: networks.csv, ranking.csv, ranking.md, summary.json, best_penn.json, best_nnn.json",
    )
    hp.add_argument(
        "--grid",
        default="thesis",
        metavar="G",
        help="thesis (864 networks, the default), small (64) or a grid YAML file",
    )
    hp.add_argument(
        "--loss", choices=["scaled", "thesis"], help="scaled (the default) or thesis (Eq. 3.7); replaces the grid's"
    )
    hp.add_argument("--executor", choices=["local", "ray"], default="local", help="local processes (default) or Ray")
    hp.add_argument(
        "--workers", type=_positive_int, metavar="N", help="worker processes or local Ray CPUs (default: every core)"
    )
    hp.add_argument("--ray-address", metavar="A", help="with --executor ray: a running cluster (default: a local one)")
    hp.add_argument(
        "--cache-dir", type=Path, metavar="D", help="JAX's compilation cache (default $XDG_CACHE_HOME/daror/jax)"
    )
    hp.add_argument("--force", action="store_true", help="write into a folder that is not empty (replaces our files)")
    hp.set_defaults(handler=cmd_hpsearch)

    con = commands.add_parser(
        "console",
        help="operator console session: typed at a terminal, a --script, or lines piped in (audit log in --out)",
    )
    con.add_argument("--hal", choices=["sim", "can-sim", "can"], help="backend (default sim)")
    con.add_argument("--scenario", help="simulated plant: a scenario name or .yaml (default exo_dummy_arm)")
    con.add_argument("--hal-config", type=Path, metavar="FILE", help="HAL configuration YAML (instead of --hal)")
    con.add_argument(
        "--script", type=Path, help="run these console lines, all checked first (lock-step unless --clock says)"
    )
    con.add_argument("--settings", type=Path, help="session settings YAML (default: the built-in settings)")
    con.add_argument("--spec", type=Path, help="FSM spec (default: fsm_spec.yaml of the repository)")
    con.add_argument("--out", type=Path, help="session directory (default sessions/DATE-TIME)")
    con.add_argument("--realtime", action="store_true", help="the same as --clock realtime")
    con.add_argument(
        "--clock",
        choices=["paced", "realtime", "lockstep"],
        help="paced: simulated time follows the wall clock, a stall of the PC delays it (typed or --web on a "
        "simulated backend); realtime: the overrun watchdog faults a stall (hardware); lockstep: as fast as the CPU "
        "allows (scripts, pipes). docs/loop.md",
    )
    con.add_argument("--web", action="store_true", help="also serve the console in a browser (live; web extra)")
    con.add_argument("--port", type=int, default=8765, help="with --web: the port (default 8765)")
    con.add_argument(
        "--host", default="127.0.0.1", help="with --web: the address (default 127.0.0.1; the printed URL has the token)"
    )
    con.add_argument(
        "--no-token",
        action="store_true",
        help="with --web on the loopback only: ask no token (any program on this computer can then drive the robot)",
    )
    con.set_defaults(handler=cmd_console)

    hil = commands.add_parser(
        "hil",
        help="hardware-in-the-loop: a console script over simulated CANopen drives (lock-step), with the bus log",
    )
    hil.add_argument("--script", type=Path, required=True, help="console lines, all checked before anything runs")
    hil.add_argument("--out", type=Path, required=True, help="folder: can.log, hil.json, the session and audit files")
    hil.add_argument("--rate-hz", type=float, help="loop and SYNC rate (default: the highest the bus load allows)")
    hil.add_argument("--scenario", help="simulated plant behind the drives (default exo_dummy_arm)")
    hil.add_argument(
        "--fault", action="append", metavar="KIND:NODE@T_S",
        help="inject a bus fault into node NODE at robot time T_S (repeatable); KIND: " + ", ".join(
            ("heartbeat_loss", "emcy", "frozen_pdo", "drive_fault", "drop_frames"))
            + "; or a fault of the bus itself, KIND@T_S: bus_off, error_passive",
    )  # fmt: skip
    hil.add_argument("--settings", type=Path, help="session settings YAML (default: the built-in settings)")
    hil.add_argument("--spec", type=Path, help="FSM spec (default: fsm_spec.yaml of the repository)")
    hil.add_argument(
        "--hal-config",
        type=Path,
        help="robot file (backend can or can-sim): its nodes run on simulated drives built from their EDS "
        "(default: the DAROR-01's four drives)",
    )
    hil.set_defaults(handler=cmd_hil)

    fsm = commands.add_parser("fsm", help="the safety FSM spec: check it, draw it, export its JSON Schema")
    fsm_cmds = fsm.add_subparsers(dest="fsm_command", required=True, metavar="WHAT")
    check = fsm_cmds.add_parser("check", help="validate a spec and print its states and transitions")
    check.add_argument("spec", nargs="?", type=Path, help="spec file (default: fsm_spec.yaml of the repository)")
    check.set_defaults(handler=cmd_fsm_check)
    diagram = fsm_cmds.add_parser("diagram", help="the spec as a Mermaid state diagram (docs/fsm.md)")
    diagram.add_argument("spec", nargs="?", type=Path, help="spec file (default: fsm_spec.yaml of the repository)")
    diagram.add_argument("--out", type=Path, help="write here instead of standard output")
    diagram.set_defaults(handler=cmd_fsm_diagram)
    schema = fsm_cmds.add_parser("schema", help="the JSON Schema of fsm_spec.yaml (for editors)")
    schema.add_argument("--out", type=Path, help="write here instead of standard output")
    schema.set_defaults(handler=cmd_fsm_schema)

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
    bench.set_defaults(handler=cmd_bench)

    rt = commands.add_parser(
        "rt-check", help="can this PC run the robot's loop at its rate? the real loop measured (docs/loop.md)"
    )
    rt.add_argument("--seconds", type=float, default=30.0, help="how long to measure, s (default 30)")
    rt.add_argument("--hal", choices=["sim", "can-sim", "can"], help="the backend whose rate is checked (default sim)")
    rt.add_argument("--hal-config", type=Path, metavar="FILE", help="HAL configuration YAML: its backend's rate")
    rt.add_argument("--json", type=Path, metavar="FILE", help="write the report as JSON here")
    rt.set_defaults(handler=cmd_rt_check, scenario=None)

    from daror_runtime.commissioning.commands import add_can_parser  # daror can scan|check|zero|tare

    add_can_parser(commands)
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
    limit_blas_threads()
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.log_level or "warning", args.log_json)
    command = " ".join(
        x
        for x in (
            args.command,
            getattr(args, "simulate_command", None),
            getattr(args, "fsm_command", None),
            getattr(args, "study_command", None),
            getattr(args, "protocol_command", None),
            getattr(args, "can_command", None),
        )
        if x
    )
    handler: Handler = args.handler
    try:
        return handler(args, _console())
    except InputError as exc:
        log.info("refused", command=command, reason=str(exc))
        sys.stderr.write(f"daror {command}: error: {exc}\n")
        return 2
    except DarorError as exc:
        # the user's line first: the log is written by its own thread, which may come before or after
        sys.stderr.write(f"daror {command}: failed: {exc}\n")
        sys.stderr.flush()
        log.error("failed", command=command, reason=str(exc))
        return 1
    except KeyboardInterrupt:
        sys.stderr.write(f"daror {command}: interrupted\n")
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
