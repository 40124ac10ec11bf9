"""What ``daror residual`` writes into its output folder.

* ``summary.json``: exactly the document of docs/residual.md, "summary.json" (other code reads it);
* ``diagnosis.json``: everything behind it (every round's candidates and their evidence, the
  residual's correlates, the settings), for a person who wants to check the decision;
* ``report.md``: the readable report: before/after RMSE and nRMSE per joint on the
  validation data, the effects found with their physical parameters, the candidates, what
  remains unexplained, and the plots;
* ``residual_signals.png``: the training residual of the base model (and of the augmented
  model) against each candidate's signal, per joint;
* ``before_after.png``: validation torque, base and augmented model per joint (like Fig. 5.2);
* ``hysteresis.png``, only when the model carries a hysteresis (:mod:`.hysteresis`): per joint
  that carries it, each point's residual without the hysteresis term against its play-operator
  state, with the fitted line. A run without one removes an earlier run's;
* ``model.json``: the augmented model, an ordinary model file;
* with ``--learned`` (:mod:`.learned`): a ``learned`` block in the summary, the diagnosis and the
  report, and ``model_learned.json`` (the augmented model plus a PENN residual, kind
  ``penn-residual``) only when the remainder was conservative and the PENN validated. A run that
  writes none removes an earlier run's, so the folder never holds a learned model its summary
  does not describe.

Every file is written to a temporary name and renamed, so a failure leaves no partial file.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import DataError
from daror_runtime.models.files import model_document, training_summary
from daror_runtime.models.metrics import ErrorMetrics
from daror_runtime.residual.diagnosis import Closure, Diagnosis
from daror_runtime.residual.learned import MIN_CONSERVATIVE_SHARE, MIN_LEARNED_GAIN, LearnedRemainder
from daror_runtime.residual.model import AugmentedModel
from daror_runtime.residual.travel import TravelChoice
from daror_runtime.util.atomic import atomic_path, write_text_atomic
from hal.robot import N_JOINTS, FloatArray

SUMMARY_KEYS = (
    "base_model",
    "rmse_before",
    "rmse_after",
    "nrmse_before",
    "nrmse_after",
    "rmse_per_joint_before",
    "rmse_per_joint_after",
    "effects",
    "unexplained",
)


def summary_document(diagnosis: Diagnosis, result: Closure, learned: LearnedRemainder | None = None) -> dict[str, Any]:
    """``DIR/summary.json`` as docs/residual.md specifies; all RMSE figures on the validation file.

    The key ``learned`` follows :data:`SUMMARY_KEYS` only when the learned step ran, and
    ``undetermined_state`` only when validation points have a hysteresis state no log determines.
    """
    document: dict[str, Any] = {
        "base_model": diagnosis.base_kind,
        "rmse_before": result.before.rmse_nm,
        "rmse_after": result.after.rmse_nm,
        "nrmse_before": result.before.nrmse,
        "nrmse_after": result.after.nrmse,
        "rmse_per_joint_before": list(result.before.rmse_per_joint_nm),
        "rmse_per_joint_after": list(result.after.rmse_per_joint_nm),
        "effects": [
            {
                "name": f.effect.family,
                "joints": [] if f.effect.joint is None else [f.effect.joint],
                "parameters": f.parameters,
                "rmse_gain": result.rmse_gain_nm(i),
            }
            for i, f in enumerate(diagnosis.found)
        ],
        "unexplained": diagnosis.unexplained,
    }
    if learned is not None:
        document["learned"] = learned.to_dict()
    unknown = result.undetermined
    if unknown is not None:
        document["undetermined_state"] = {
            "n_points": unknown.n_points,
            "t_s": list(unknown.t_s),
            "joints": list(unknown.joints),
            "rmse_before": unknown.before.rmse_nm if unknown.before is not None else None,
            "rmse_after": unknown.after.rmse_nm if unknown.after is not None else None,
        }
    return document


def direction_signal_document(travel: TravelChoice) -> dict[str, Any]:
    """What weighing the direction offset against the hysteresis measured (``diagnosis.json``)."""
    return {
        "chosen": "hysteresis" if travel.hysteresis else "direction_offset",
        "path": "raw log" if travel.from_raw_log else "stationary points in order",
        "travel_rad": [float(v) for v in travel.travel_rad],
        "bic_direction_offset": travel.bic_direction,
        "bic_hysteresis": travel.bic_hysteresis,
        "profile": [{"travel_rad": r, "training_rmse_nm": rmse} for r, rmse in travel.profile],
    }


def diagnosis_document(
    diagnosis: Diagnosis,
    result: Closure,
    train: StationaryDataset,
    validate: StationaryDataset,
    learned: LearnedRemainder | None = None,
) -> dict[str, Any]:
    """``DIR/diagnosis.json``: the evidence behind the summary."""
    document: dict[str, Any] = {
        "train": {"source": train.source, "n_points": len(train)},
        "validate": {"source": validate.source, "n_points": len(validate)},
        "base_model": diagnosis.base_kind,
        "settings": asdict(diagnosis.settings),
        "training_rmse_before": float(np.sqrt(diagnosis.base_fit.rss / diagnosis.base_fit.n_rows)),
        "training_rmse_after": float(np.sqrt(diagnosis.final_fit.rss / diagnosis.final_fit.n_rows)),
        "validation_before": result.before.to_dict(),
        "validation_after": result.after.to_dict(),
        "found": [
            {"effect": f.effect.family, "joint": f.effect.joint, "sentence": f.sentence, **f.evidence.to_dict()}
            for f in diagnosis.found
        ],
        "rounds": [[e.to_dict() for e in round_] for round_ in diagnosis.rounds],
        "correlates": [c.to_dict() for c in diagnosis.correlates],
        "unexplained": diagnosis.unexplained,
        "notes": diagnosis.notes,
        "duration_s": diagnosis.duration_s,
    }
    if learned is not None:
        document["learned"] = {
            **learned.to_dict(),
            "penn_share": learned.penn_share,
            "min_learned_gain": MIN_LEARNED_GAIN,
            "min_conservative_share": MIN_CONSERVATIVE_SHARE,
            "training_notes": learned.notes,
            "duration_s": learned.duration_s,
        }
    return document


def _metrics_table(before: ErrorMetrics, after: ErrorMetrics) -> list[str]:
    lines = [
        "| | RMSE before (Nm) | RMSE after (Nm) | change |",
        "|---|---|---|---|",
    ]
    for j in range(N_JOINTS):
        b, a = before.rmse_per_joint_nm[j], after.rmse_per_joint_nm[j]
        lines.append(f"| joint {j + 1} | {b:.4f} | {a:.4f} | {_change(b, a)} |")
    lines.append(
        f"| **all joints** | **{before.rmse_nm:.4f}** | **{after.rmse_nm:.4f}** | {_change(before.rmse_nm, after.rmse_nm)} |"
    )
    lines.append(
        f"| nRMSE (Eq. 4.32) | {before.nrmse:.4f} | {after.nrmse:.4f} | {_change(before.nrmse, after.nrmse)} |"
    )
    return lines


def _undetermined_lines(result: Closure, n_points: int) -> list[str]:
    """What the report says of validation points whose hysteresis state no log determines (nothing when none)."""
    unknown = result.undetermined
    if unknown is None:
        return []
    times = ", ".join(f"{t:.1f}" for t in unknown.t_s[:5]) + (", ..." if unknown.n_points > 5 else "")
    lines = [
        f"**{unknown.n_points} of {n_points} validation points {'has' if unknown.n_points == 1 else 'have'} a "
        f"hysteresis state their run's log does not determine** (t = {times} s; joint(s) {', '.join(map(str, unknown.joints))}): the log holds no motion of "
        "those joints before the point far enough to settle it (a run that begins at rest at its first stop), "
        "so the state is taken as halfway and even a model that lacks nothing errs there by up to the "
        "hysteresis's amplitude. A limit of the data, not of the model.",
    ]
    if unknown.before is not None and unknown.after is not None:
        kept = n_points - unknown.n_points
        lines[0] += (
            f" On the other {kept} points: RMSE {unknown.before.rmse_nm:.4f} -> {unknown.after.rmse_nm:.4f} Nm "
            f"(per joint after: {', '.join(f'{v:.4f}' for v in unknown.after.rmse_per_joint_nm)})."
        )
    return [*lines, ""]


def _change(before: float, after: float) -> str:
    return f"{(after / before - 1) * 100:+.1f} %" if before > 0 else "n/a"


def effect_rmse_nm(closure: Closure, index: int) -> tuple[float, float]:
    """The validation RMSE (Nm) before and after effect ``index`` (0-based, in the order found) was added."""
    before = closure.before.rmse_nm if index == 0 else closure.rmse_after_each_nm[index - 1]
    return before, closure.rmse_after_each_nm[index]


def rmse_change(before_nm: float, after_nm: float, digits: int = 4) -> str:
    """A change of RMSE as a change: ``validation RMSE 0.6200 -> 0.4191 Nm (-0.2009 Nm)``.

    Both RMSEs are shown (an RMSE is never negative); the signed figure in brackets is the change
    (Nm, negative when the error fell). ``digits``: decimals of every figure.
    """
    return f"validation RMSE {before_nm:.{digits}f} -> {after_nm:.{digits}f} Nm ({after_nm - before_nm:+.{digits}f} Nm)"


def _learned_section(learned: LearnedRemainder) -> list[str]:
    """The report's section on the learned remainder (``--learned``)."""
    lines = [
        "## What remains, learned (`--learned`)",
        "",
        "Two networks learned what the named effects leave in the training data: a PENN (a potential: "
        "conservative by construction) and an NNN (any field of q). Validation RMSE (Nm):",
        "",
        "| | joint 1 | joint 2 | joint 3 | joint 4 | all joints |",
        "|---|---|---|---|---|---|",
    ]
    for label, metrics in (
        ("named effects (model.json)", learned.named),
        ("+ PENN residual (conservative)", learned.penn),
        ("+ NNN residual (not conservative)", learned.nnn),
    ):
        joints = " | ".join(f"{v:.4f}" for v in metrics.rmse_per_joint_nm)
        lines.append(f"| {label} | {joints} | **{metrics.rmse_nm:.4f}** |")
    share = learned.penn_share
    lines += [
        "",
        f"**{learned.sentence}**",
        "",
        f"- closed by the PENN (conservative part): {learned.conservative_part_nm:.4f} Nm RMS; closed only by "
        f"the NNN (non-conservative part): {learned.non_conservative_part_nm:.4f} Nm RMS; the PENN's share of "
        f"what the NNN closes: {'n/a' if share is None else f'{share:.2f}'} (conservative at "
        f">= {MIN_CONSERVATIVE_SHARE}, something to learn when a network lowers the RMSE by >= {MIN_LEARNED_GAIN:.0%})",
        f"- the networks: {learned.notes['penn'][0]}; {learned.notes['nnn'][0]}; {learned.duration_s:.1f} s",
    ]
    return lines


def report_markdown(
    diagnosis: Diagnosis,
    result: Closure,
    train: StationaryDataset,
    validate: StationaryDataset,
    plots: list[str],
    learned: LearnedRemainder | None = None,
    hysteresis_plot: str | None = None,
) -> str:
    """The readable report (Markdown).

    ``plots``: the figures' file names, shown under "Plots"; ``hysteresis_plot``: the hysteresis
    figure's file name when it was written (named under "Effects found" and shown with the plots).
    """
    base = diagnosis.base_kind.upper()
    lines = [
        f"# Residual analysis: {base} + effects",
        "",
        f"- training data: `{train.source}` ({len(train)} stationary points)",
        f"- validation data: `{validate.source}` ({len(validate)} stationary points); every figure below is on it",
        f"- base model: {base}; diagnosis took {diagnosis.duration_s:.1f} s",
        "",
        "## Before and after, on the validation data",
        "",
        *_metrics_table(result.before, result.after),
        "",
        *_undetermined_lines(result, len(validate)),
        "## Effects found",
        "",
    ]
    if not diagnosis.found:
        lines.append(
            f"None. No candidate effect passed the evidence tests on top of {base}: nothing was added, "
            "and the augmented model equals the base model."
        )
    for i, f in enumerate(diagnosis.found, start=1):
        e = f.evidence
        lines.append(
            f"{i}. **{f.sentence}**. When added: {rmse_change(*effect_rmse_nm(result, i - 1))}; "
            f"held-out (training CV) RMSE {e.cv_rmse_before_nm:.4f} -> {e.cv_rmse_after_nm:.4f} Nm, "
            f"dBIC {e.delta_bic:.1f}, F test p = {e.p_value:.2g}."
        )
        if result.rmse_gain_nm(i - 1) < 0:
            lines.append(
                "   **It did not hold on the validation data** (the RMSE rose). The training data supported it, "
                "but it is not a stable property of the robot: with unexplained structure present (below), it "
                "most likely stands in for that structure."
            )
    if hysteresis_plot is not None:
        lines += [
            "",
            f"The hysteresis against the data: [{hysteresis_plot}]({hysteresis_plot}) plots, per joint that "
            "carries it, each point's residual without the hysteresis term (Nm; training and validation points) "
            "against its play-operator state s_j, with the fitted line gain_j d_j s_j.",
        ]
    lines += ["", "## Candidates of the last round", ""]
    if diagnosis.rounds:
        lines += [
            "| candidate | verdict | outside the model's span | dBIC | p | held-out RMSE change |",
            "|---|---|---|---|---|---|",
        ]
        for e in diagnosis.rounds[-1]:
            lines.append(
                f"| {e.effect.label} | {e.verdict} | {e.orthogonal_fraction:.3g} | {e.delta_bic:.1f} | "
                f"{e.p_value:.2g} | {-e.cv_gain * 100:+.1f} % |"
            )
    lines += ["", "## What remains", ""]
    structured = diagnosis.structured_correlates
    if structured:
        lines.append(
            "**Unexplained structure remains**: the residual of the augmented model still depends on signals "
            "that no effect family explains:"
        )
        lines.append("")
        for c in structured[:8]:
            lines.append(
                f"- joint {c.joint} residual against `{c.signal}`: R^2 = {c.r2:.2f}, r = {c.pearson_r:+.2f}, p = {c.p_value:.2g}"
            )
    else:
        strongest = diagnosis.correlates[0] if diagnosis.correlates else None
        detail = (
            f" (strongest: joint {strongest.joint} against `{strongest.signal}`, R^2 = {strongest.r2:.3f})"
            if strongest
            else ""
        )
        lines.append(f"No structure left: the residual depends on no tested signal{detail}.")
    if learned is not None:
        lines += ["", *_learned_section(learned)]
    if diagnosis.notes:
        lines += ["", "## Notes", "", *[f"- {n}" for n in diagnosis.notes]]
    lines += ["", "## Plots", ""]
    lines += [f"![{p}]({p})" for p in (*plots, *([hysteresis_plot] if hysteresis_plot else []))]
    return "\n".join(lines) + "\n"


def _save_figure(figure: Any, path: Path) -> None:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buffer.getvalue())


#: Points drawn per scatter or line at most: beyond this a PNG shows no more (1,100 px wide), and
#: drawing a million markers per panel takes tens of seconds and hundreds of MB.
MAX_PLOTTED_POINTS = 20_000


def _plotted(n_points: int) -> tuple[slice, str]:
    """Every k-th point when there are more than :data:`MAX_PLOTTED_POINTS`, and a note saying so."""
    step = -(-n_points // MAX_PLOTTED_POINTS)
    if step <= 1:
        return slice(None), ""
    return slice(None, None, step), f" (one point in {step} of {n_points:,} shown)"


def plot_residual_signals(diagnosis: Diagnosis, train: StationaryDataset, path: Path) -> None:
    """Training residual, base (grey) and augmented (blue), against each candidate's signal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown, note = _plotted(len(train))
    train = train.subset(shown)
    before, after = diagnosis.base_fit.residual_nm[shown], diagnosis.final_fit.residual_nm[shown]
    model_torque = train.tau_nm - before
    signals: list[tuple[str, Any]] = [
        ("joint angle q_j (deg)  [joint_stiffness, encoder_offset]", lambda j: np.degrees(train.q_rad[:, j])),
        ("modelled torque (Nm)  [torque_gain]", lambda j: model_torque[:, j]),
    ]
    if train.direction is not None:
        direction = train.direction
        signals.insert(0, ("last motion dir_j  [direction_offset]", lambda j: direction[:, j]))
    time_values = train.t_s if train.t_s is not None else np.arange(len(train), dtype=float)
    signals.append(
        ("time t (s)  [none: drift]" if train.t_s is not None else "sample order  [none: drift]", lambda j: time_values)
    )
    figure, axes = plt.subplots(N_JOINTS, len(signals), figsize=(4.2 * len(signals), 2.6 * N_JOINTS), squeeze=False)
    rng = np.random.default_rng(0)
    for j in range(N_JOINTS):
        for c, (label, values) in enumerate(signals):
            ax = axes[j, c]
            x = values(j)
            jitter = rng.uniform(-0.15, 0.15, x.shape) if label.startswith("last motion") else 0.0
            ax.scatter(x + jitter, before[:, j], s=3, color="0.6", label=f"{diagnosis.base_kind.upper()}")
            ax.scatter(x + jitter, after[:, j], s=3, color="tab:blue", label="augmented")
            ax.axhline(0.0, color="k", linewidth=0.6)
            if j == N_JOINTS - 1:
                ax.set_xlabel(label)
            if c == 0:
                ax.set_ylabel(f"joint {j + 1} residual (Nm)")
    axes[0, 0].legend(loc="upper right", fontsize=7, markerscale=3)
    figure.suptitle(f"Training residual against each candidate's signal{note}")
    figure.tight_layout()
    _save_figure(figure, path)
    plt.close(figure)


def plot_before_after(diagnosis: Diagnosis, model: AugmentedModel, validate: StationaryDataset, path: Path) -> None:
    """Validation torque, base and augmented model per joint (like the thesis's Fig. 5.2)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown, note = _plotted(len(validate))
    index = np.arange(len(validate))[shown]
    validate = validate.subset(shown)
    base = diagnosis.base_fit.predict(validate)
    augmented = model.predict(validate.q_rad, validate.direction)
    figure, axes = plt.subplots(N_JOINTS, 1, figsize=(11, 2.3 * N_JOINTS), sharex=True)
    for j in range(N_JOINTS):
        ax = axes[j]
        ax.plot(index, validate.tau_nm[:, j], ".", color="k", markersize=3, label="measured")
        ax.plot(index, base[:, j], "-", color="0.55", linewidth=1, label=diagnosis.base_kind.upper())
        ax.plot(index, augmented[:, j], "-", color="tab:blue", linewidth=1, label="augmented")
        ax.set_ylabel(f"tau{j + 1} (Nm)")
    axes[0].legend(loc="upper right", fontsize=8, ncol=3)
    axes[-1].set_xlabel("validation point")
    figure.suptitle(f"Validation data and the models, before and after{note}")
    figure.tight_layout()
    _save_figure(figure, path)
    plt.close(figure)


@dataclass(frozen=True)
class HysteresisCurve:
    """What ``hysteresis.png`` draws for one joint of one dataset.

    ``states`` and ``residual_nm`` are per point of the dataset, in its order; the line is the
    model's hysteresis term ``gain * amplitude_nm * s`` over ``line_states`` (s from -1 to 1).
    """

    joint: int  # 1-based
    amplitude_nm: float  # d_j, Nm
    travel_rad: float  # r_j, rad
    gain: float  # the joint's torque gain, which scales the term as it scales the torque
    states: FloatArray  # (points,) the play operator's state s_j of each point, in [-1, 1]
    residual_nm: FloatArray  # (points,) tau_j minus the model without its direction term, Nm
    line_states: FloatArray  # (n,) s from -1 to 1
    line_nm: FloatArray  # (n,) gain * amplitude_nm * line_states, Nm


def carries_hysteresis(model: AugmentedModel) -> bool:
    """True when ``model`` holds a hysteresis: travel constants and a nonzero amplitude on some joint."""
    return model.spec.hysteresis_travel_rad is not None and any(d != 0.0 for d in model.spec.hysteresis_nm)


def hysteresis_curve_data(model: AugmentedModel, dataset: StationaryDataset) -> list[HysteresisCurve]:
    """Per joint that carries the model's hysteresis: each point's state and residual, and the fitted line.

    ``dataset.direction`` must hold the hysteresis states for the model's travel constants (as
    :func:`daror_runtime.residual.travel.with_signal` makes it); the residual is
    ``tau_j - model.predict(q, None)[:, j]`` (Nm): what the sensors read beyond the modelled
    torque, the hysteresis term included. An empty list for a model without a hysteresis.

    Raises:
        DataError: the model carries a hysteresis but ``dataset`` has no direction signal, or one
            of another shape, or states outside [-1, 1].
    """
    if not carries_hysteresis(model):
        return []
    if dataset.direction is None:
        raise DataError(f"{dataset.source}: no direction signal; expected the hysteresis states s1..s4 of each point")
    states = np.asarray(dataset.direction, dtype=float)
    if states.shape != dataset.q_rad.shape:
        raise DataError(
            f"{dataset.source}: direction signal of shape {states.shape}; expected the hysteresis states, "
            f"one per joint and point {dataset.q_rad.shape}"
        )
    if not np.all(np.abs(states) <= 1.0 + 1e-9):  # a window's mean of states may round past 1
        raise DataError(f"{dataset.source}: direction signal outside [-1, 1]; expected hysteresis states")
    residual = dataset.tau_nm - model.predict(dataset.q_rad, None)
    travel = model.spec.hysteresis_travel_rad or []
    line_states = np.linspace(-1.0, 1.0, 101)
    curves = []
    for j, amplitude in enumerate(model.spec.hysteresis_nm):
        if amplitude == 0.0:
            continue
        gain = float(model.spec.torque_gain[j])
        curves.append(
            HysteresisCurve(
                joint=j + 1,
                amplitude_nm=float(amplitude),
                travel_rad=float(travel[j]),
                gain=gain,
                states=states[:, j].copy(),
                residual_nm=residual[:, j].copy(),
                line_states=line_states,
                line_nm=gain * float(amplitude) * line_states,
            )
        )
    return curves


def plot_hysteresis(model: AugmentedModel, train: StationaryDataset, validate: StationaryDataset, path: Path) -> None:
    """Per joint with a hysteresis: the residual without its term against the state, and the fitted line.

    Raises:
        DataError: see :func:`hysteresis_curve_data`.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    train_shown, train_note = _plotted(len(train))
    validate_shown, validate_note = _plotted(len(validate))
    curves = hysteresis_curve_data(model, train.subset(train_shown))
    checks = hysteresis_curve_data(model, validate.subset(validate_shown))
    figure, axes = plt.subplots(1, len(curves), figsize=(4.6 * len(curves), 3.8), squeeze=False)
    for ax, curve, check in zip(axes[0], curves, checks, strict=True):
        ax.scatter(curve.states, curve.residual_nm, s=4, color="0.55", label=f"training{train_note}")
        ax.scatter(
            check.states, check.residual_nm, s=14, marker="x", color="tab:orange", label=f"validation{validate_note}"
        )
        ax.plot(curve.line_states, curve.line_nm, "-", color="tab:blue", linewidth=1.5, label="fitted gain d s")
        ax.axhline(0.0, color="k", linewidth=0.6)
        ax.set_xlim(-1.05, 1.05)
        ax.set_xlabel(f"hysteresis state s{curve.joint}")
        ax.set_title(f"joint {curve.joint}: {curve.amplitude_nm:+.3g} Nm over {curve.travel_rad * 1e3:.3g} mrad")
    axes[0, 0].set_ylabel("residual without the hysteresis (Nm)")
    axes[0, 0].legend(loc="upper left", fontsize=7, markerscale=2)
    figure.suptitle("The hysteresis fitted against the data")
    figure.tight_layout()
    _save_figure(figure, path)
    plt.close(figure)


REPORT_FILES = ("residual_signals.png", "before_after.png", "model.json", "diagnosis.json", "report.md", "summary.json")
#: Written with ``--learned`` when the remainder was conservative and the PENN validated.
LEARNED_MODEL_FILE = "model_learned.json"
#: Written when the model carries a hysteresis (:func:`carries_hysteresis`).
HYSTERESIS_PLOT_FILE = "hysteresis.png"
#: Files a run writes only sometimes, besides :data:`REPORT_FILES`: a run that does not write one
#: removes an earlier run's, so the folder never holds a file its summary does not describe.
OPTIONAL_FILES = (LEARNED_MODEL_FILE, HYSTERESIS_PLOT_FILE)


def write_report(
    out_dir: Path | str,
    diagnosis: Diagnosis,
    result: Closure,
    model: AugmentedModel,
    train: StationaryDataset,
    validate: StationaryDataset,
    train_path: Path | str | None = None,
    learned: LearnedRemainder | None = None,
    travel: TravelChoice | None = None,
    signal_map_notes: tuple[str, ...] = (),
) -> dict[str, Path]:
    """Write every file of the report into ``out_dir``; returns their paths by name.

    ``travel``: the direction offset weighed against the hysteresis (:mod:`.travel`), when it was.
    ``signal_map_notes``: what to say of data whose signal map failed and was trusted (the model
    files' ``training.signal_map`` and ``summary.json``'s ``signal_map``; absent when empty).

    The files are written into a temporary folder beside ``out_dir`` and moved in only when all
    of them exist (``summary.json`` last): a failure leaves ``out_dir`` as it was. An earlier
    run's :data:`OPTIONAL_FILES` (the learned model, the hysteresis plot) are removed when this
    run writes none. The returned dict is keyed by file name; it holds an optional file only
    when it was written.

    Raises:
        DataError: the model carries a hysteresis but the datasets hold no hysteresis states
            (see :func:`hysteresis_curve_data`).
    """
    out = Path(out_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        optional = _write_files(
            staging, diagnosis, result, model, train, validate, train_path, learned, travel, signal_map_notes
        )
        names = (*optional, *REPORT_FILES)
        out.mkdir(exist_ok=True)
        for name in OPTIONAL_FILES:
            if name not in optional:
                (out / name).unlink(missing_ok=True)
        for name in names:
            os.replace(staging / name, out / name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return {name: out / name for name in names}


def _write_files(
    out: Path,
    diagnosis: Diagnosis,
    result: Closure,
    model: AugmentedModel,
    train: StationaryDataset,
    validate: StationaryDataset,
    train_path: Path | str | None,
    learned: LearnedRemainder | None,
    travel: TravelChoice | None = None,
    signal_map_notes: tuple[str, ...] = (),
) -> tuple[str, ...]:
    """Write the report's files into ``out``; the names of the :data:`OPTIONAL_FILES` written."""
    optional: list[str] = []
    paths = {
        "signals_plot": out / "residual_signals.png",
        "before_after_plot": out / "before_after.png",
        "model": out / "model.json",
        "diagnosis": out / "diagnosis.json",
        "report": out / "report.md",
        "summary": out / "summary.json",
    }
    plot_residual_signals(diagnosis, train, paths["signals_plot"])
    plot_before_after(diagnosis, model, validate, paths["before_after_plot"])
    if carries_hysteresis(model):
        plot_hysteresis(model, train, validate, out / HYSTERESIS_PLOT_FILE)
        optional.append(HYSTERESIS_PLOT_FILE)
    summary = training_summary(train, train_path)
    if signal_map_notes:
        summary = summary.model_copy(update={"signal_map": "; ".join(signal_map_notes)})
    document = model_document(model, summary)
    write_text_atomic(paths["model"], json.dumps(document, indent=2, allow_nan=False) + "\n")
    if learned is not None and learned.model is not None:
        learned_document = model_document(learned.model, summary)
        write_text_atomic(out / LEARNED_MODEL_FILE, json.dumps(learned_document, indent=2, allow_nan=False) + "\n")
        optional.append(LEARNED_MODEL_FILE)
    evidence = diagnosis_document(diagnosis, result, train, validate, learned)
    if travel is not None:
        evidence["direction_signal"] = direction_signal_document(travel)
    write_text_atomic(paths["diagnosis"], _json(evidence))
    plots = [paths["before_after_plot"].name, paths["signals_plot"].name]
    hysteresis_plot = HYSTERESIS_PLOT_FILE if HYSTERESIS_PLOT_FILE in optional else None
    write_text_atomic(
        paths["report"], report_markdown(diagnosis, result, train, validate, plots, learned, hysteresis_plot)
    )
    # The summary last: its presence says the whole report is there.
    summary_json = summary_document(diagnosis, result, learned)
    if signal_map_notes:
        summary_json["signal_map"] = list(signal_map_notes)
    write_text_atomic(paths["summary"], _json(summary_json))
    return tuple(optional)


def _json(document: dict[str, Any]) -> str:
    """Strict JSON (no NaN): figures that could not be measured are null."""
    return json.dumps(_clean(document), indent=2, allow_nan=False) + "\n"


def _clean(value: object) -> object:
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
