"""``daror demo``: a full simulated session, then the modelling pipeline, with a report.

Part 1 (:mod:`daror_runtime.demo.rehearsal`): a session on the simulated plant with the Dummy
Arm, start to compensation through every state of ``fsm_spec.yaml``, driven by the packaged
console script; the report lists the transitions, the identification, the model's validation and
what the robot carries once the pilot relaxes.

Part 3 (:mod:`daror_runtime.residual`): the session's own identification data go through
``daror residual``: PLF+'s residual traced to physical effects, added, before/after reported.

Part 2, for dataset A (``exo``) and B (``exo_dummy_arm``): record a training and a validation set of
stationary points, build the A Priori model and fit PLF and PLF+, evaluate them on the
validation set (Table III) and run the closed-path energy test (Table IV). Everything lands in
the output directory: datasets, model files, ``summary.json`` and a Markdown ``report.md``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import structlog
from rich.console import Console
from rich.table import Table

from daror_runtime.data.load import write_dataset
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.demo.rehearsal import SessionReport
from daror_runtime.errors import DarorError
from daror_runtime.models.compare import (
    THESIS_TABLE_III,
    THESIS_TABLE_IV,
    Evaluation,
    cvf_document,
    cvf_models,
    cvf_table,
    evaluate_models,
    evaluation_document,
)
from daror_runtime.models.files import save_model, training_summary
from daror_runtime.models.registry import fit_model, installation_options
from daror_runtime.util.atomic import write_text_atomic
from hal.robot import load_description
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary

log = structlog.get_logger(__name__)

#: The kinds the demo fits and compares with the thesis's tables: a choice of the demo, checked
#: against the model registry by the tests (each registered, and in THESIS_TABLE_III).
DEMO_KINDS = ("ap", "plf", "plf+")
#: The simulated plant of the demo's session: the Dummy Arm (dataset B), whose truth gives the floor.
DEMO_SCENARIO = "exo_dummy_arm"


@dataclass(frozen=True)
class DatasetRun:
    label: str
    scenario: str
    evaluations: list[Evaluation]
    models: list[Any]


def _stationary(points: Any) -> StationaryDataset:
    return StationaryDataset(points.q_rad, points.tau_nm, points.direction, points.t_s)


def _run_dataset(label: str, scenario_name: str, out: Path, console: Console) -> DatasetRun:
    scenario = load_scenario(scenario_name)
    description = load_description(scenario.robot)
    paths = {kind: out / f"dataset_{label}_{kind}.csv" for kind in ("training", "validation")}
    data = {}
    for trajectory, path in paths.items():
        data[trajectory] = _stationary(generate_stationary(scenario, trajectory))  # type: ignore[arg-type]
        write_dataset(path, data[trajectory])
    console.print(
        f"dataset {label} ({scenario.name}): {len(data['training'])} training and "
        f"{len(data['validation'])} validation stationary points"
    )
    models = []
    for kind in DEMO_KINDS:
        options = installation_options(kind, dummy_arm=scenario.dummy_arm is not None)
        result = fit_model(kind, data["training"], description, options)
        save_model(
            out / f"model_{label}_{kind.replace('+', '_plus')}.json",
            result.model,
            training_summary(data["training"], paths["training"]),
            result.report,
        )
        models.append(result.model)
        rank = f", rank {result.report.rank}/{result.report.n_parameters}" if result.report.rank else ""
        console.print(f"  {result.model.display_name:9s} built in {result.report.duration_s * 1e3:6.1f} ms{rank}")
    evaluations = evaluate_models(models, data["validation"])
    log.info("dataset evaluated", dataset=label, **{e.kind: round(e.metrics.rmse_nm, 4) for e in evaluations})
    return DatasetRun(label, scenario.name, evaluations, models)


def _table_iii(runs: list[DatasetRun]) -> tuple[Table, str]:
    table = Table(title="Validation errors next to the thesis's Table III")
    headers = ["Model"]
    for run in runs:
        headers += [f"RMSE {run.label} (Nm)", "thesis", f"nRMSE {run.label}", "thesis"]
    for h in headers:
        table.add_column(h, justify="left" if h == "Model" else "right")
    md = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    for i, kind in enumerate(DEMO_KINDS):
        row = [runs[0].evaluations[i].name]
        for k, run in enumerate(runs):
            e = run.evaluations[i].metrics
            thesis = THESIS_TABLE_III[kind]
            row += [f"{e.rmse_nm:.3g}", f"{thesis[2 * k]:.3g}", f"{e.nrmse:.3g}", f"{thesis[2 * k + 1]:.3g}"]
        table.add_row(*row)
        md.append("| " + " | ".join(row) + " |")
    return table, "\n".join(md)


def _cvf_markdown(document: dict[str, Any]) -> str:
    lines = [
        "| Model | dV at pi/400 (J) | pi/4000 | pi/40000 | thesis (same steps) | verdict |",
        "|---|---|---|---|---|---|",
    ]
    for m in document["models"]:
        thesis = THESIS_TABLE_IV.get(m["kind"])
        ref = ", ".join(f"{v:.3g}" for v in thesis) if thesis else "-"
        values = " | ".join(f"{s['dV']:.3g}" for s in m["steps"])
        lines.append(
            f"| {m['name']} | {values} | {ref} | {'conservative' if m['conservative'] else 'NOT conservative'} |"
        )
    return "\n".join(lines)


def _session_tables(session: SessionReport) -> tuple[Table, str]:
    """What the session did, for the terminal and for the Markdown report."""
    table = Table(
        title=f"Session {session.session_id}: {len(session.transitions)} transitions, ends in {session.final_state}"
    )
    for column in ("t (s)", "event", "from", "to"):
        table.add_column(column)
    md = ["| t (s) | event | from | to |", "|---|---|---|---|"]
    for t in session.transitions:
        row = [f"{t['t_s']:.1f}", t["event"], t["from"], t["to"]]
        table.add_row(*row)
        md.append("| " + " | ".join(row) + " |")
    model = session.status.get("model") or {}
    joints = " | ".join(f"joint {j}" for j in range(1, 5))
    md += [
        "",
        f"Robot time {session.robot_time_s:.0f} s. Identification data: "
        + ", ".join(f"{k} `{Path(v).name}`" for k, v in (session.status.get("identification_saved") or {}).items()),
        "",
        f"Model in use: {model.get('name', '-')}, validation RMSE {model.get('validation_rmse_nm', float('nan')):.3f} Nm "
        f"(validated: {model.get('validated')}).",
        "",
        f"| with the pilot relaxed, Nm | {joints} |",
        "|---|---|---|---|---|",
        "| arm's holding torque (mean abs) | " + " | ".join(f"{v:.2f}" for v in session.holding_torque_nm) + " |",
        "| torque the pilot still adds (RMS) | " + " | ".join(f"{v:.3f}" for v in session.unsupported_torque_nm) + " |",
    ]
    return table, "\n".join(md)


def _close_the_loop(session: SessionReport, out: Path, console: Console, scenario: str) -> tuple[str, dict[str, Any]]:
    """Part 3: the residual analysis on the session's identification data; its Markdown summary."""
    from daror_runtime.residual.pipeline import run_residual

    saved = session.status.get("identification_saved") or {}
    if set(saved) != {"training", "validation"}:
        raise DarorError("the session saved no training and validation data to close the loop on")
    console.print("[bold]Closing the loop on the session's measured data (PLF+ residual)[/bold]")
    run = run_residual(saved["training"], saved["validation"], out / "residual_session", load_description())
    before, after = run.closure.before, run.closure.after
    lines = [
        f"PLF+ on the session's validation points: RMSE {before.rmse_nm:.3f} Nm before, {after.rmse_nm:.3f} Nm "
        f"after adding what the data support (nRMSE {before.nrmse:.3f} -> {after.nrmse:.3f}).",
        "",
    ]
    for i, found in enumerate(run.diagnosis.found):
        lines.append(f"- found: {found.sentence} (validation RMSE {-run.closure.rmse_gain_nm(i):+.3f} Nm)")
        console.print(f"  found: {found.sentence}")
    if not run.diagnosis.found:
        lines.append("- no effect beyond PLF+ is supported by the data")
    for c in run.diagnosis.structured_correlates[:3]:
        lines.append(f"- unexplained: joint {c.joint} residual depends on {c.signal} (R^2 {c.r2:.2f})")
    lines.append("")
    lines.append("Full report: `residual_session/report.md`.")
    console.print(
        f"  RMSE {before.rmse_nm:.3f} -> {after.rmse_nm:.3f} Nm; report: {out / 'residual_session' / 'report.md'}"
    )
    floor = _floor_of_the_session(run, scenario)
    for line in floor.lines:
        console.print(f"  {line}")
    lines += ["", *floor.lines]
    return "\n".join(lines), floor.document


@dataclass(frozen=True)
class SessionFloor:
    """The demo's closure against the noise floor of its own runs (D109): what it prints and keeps."""

    lines: list[str]
    document: dict[str, Any]


def _floor_of_the_session(run: Any, scenario_name: str) -> SessionFloor:
    """The session's closure against the floor of the same runs: the plant's true hysteresis taken out (D109, D204)."""
    from daror_runtime.residual.floor import floor_of_the_same_runs

    sensors = load_scenario(scenario_name).sensors
    inputs = run.inputs
    floor = floor_of_the_same_runs(
        inputs, np.asarray(sensors.direction_error_nm), float(sensors.direction_play_rad), load_description(),
        run.unknown_state,
    )  # fmt: skip
    after, floor_nm = run.closure.after.rmse_nm, floor.after.rmse_nm
    lines = [
        f"Closure against the floor of the session's own runs (PLF+ with the plant's true hysteresis taken out, "
        f"D109): {after:.4f} Nm against {floor_nm:.4f} Nm, {after / floor_nm:.2f}x."
    ]
    document: dict[str, Any] = {"rmse_after": after, "floor": floor_nm, "ratio": after / floor_nm}
    known, known_floor = run.closure.undetermined, floor.undetermined
    if known is not None and known.after is not None and known_floor is not None and known_floor.after is not None:
        kept = len(inputs.validate) - known.n_points
        ratio = known.after.rmse_nm / known_floor.after.rmse_nm
        lines.append(
            f"Without the {known.n_points} validation point(s) whose hysteresis state no log determines "
            f"(t = {', '.join(f'{t:.1f}' for t in known.t_s)} s: the run begins at rest there), on the other {kept}: "
            f"{known.after.rmse_nm:.4f} Nm against {known_floor.after.rmse_nm:.4f} Nm, {ratio:.2f}x."
        )
        document["determined"] = {
            "n_points": kept,
            "left_out_t_s": list(known.t_s),
            "rmse_after": known.after.rmse_nm,
            "floor": known_floor.after.rmse_nm,
            "ratio": ratio,
        }
    return SessionFloor(lines, document)


def run_demo(out: Path, console: Console) -> dict[str, Any]:
    """Run the demo into ``out``; returns the summary written to ``out/summary.json``."""
    from daror_runtime.demo.rehearsal import rehearse

    out.mkdir(parents=True, exist_ok=True)
    log.info("demo started", out=str(out))
    console.print("[bold]DAROR-01: a full session on the simulated plant, start to compensation[/bold]")
    session = rehearse(out / "session", Console(quiet=True), DEMO_SCENARIO)
    session_table, session_md = _session_tables(session)
    console.print(session_table)
    console.print("[bold]DAROR-01 modelling pipeline on the simulated plant[/bold]")
    runs = [_run_dataset("A", "exo", out, console), _run_dataset("B", "exo_dummy_arm", out, console)]
    table, table_md = _table_iii(runs)
    console.print(table)
    cvf = cvf_models(runs[1].models)
    console.print(cvf_table(cvf, "Closed-path energy test, dataset B models (thesis Table IV)"))
    residual_md, floor = _close_the_loop(session, out, console, DEMO_SCENARIO)
    summary = {
        "datasets": {run.label: {"scenario": run.scenario, **evaluation_document(run.evaluations)} for run in runs},
        "cvf_B": cvf_document(cvf),
        "session": session.document(),
        "residual_session": json.loads((out / "residual_session" / "summary.json").read_text()),
        "residual_session_floor": floor,
    }
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    report = [
        "# DAROR-01 demo report",
        "",
        "## A full session on the simulated plant (Dummy Arm), start to compensation",
        "",
        session_md,
        "",
        "## Modelling pipeline",
        "",
        "Simulated stationary data (scenarios `exo` = dataset A, `exo_dummy_arm` = dataset B);",
        "errors on each validation set (Eq. 4.31-4.32), the thesis's figures beside ours.",
        "",
        table_md,
        "",
        "## Closed-path energy test (Sec. 4.4.4), dataset B models",
        "",
        _cvf_markdown(summary["cvf_B"]),
        "",
        "## Closing the loop on the session's own measurements (daror residual)",
        "",
        residual_md,
        "",
    ]
    write_text_atomic(out / "report.md", "\n".join(report))
    console.print(f"report: {out / 'report.md'}, figures: {out / 'summary.json'}")
    log.info("demo finished", out=str(out))
    return summary
