"""One pilot over months: his trend report and the export of his records (``daror pilots report|export``).

The report (``report.md``, ``report.png``, ``report.json``) follows what the research question asks
(thesis Sec. 7.4): per session, his range of motion per ISB angle, the physical parameters of the
model in use (the first moments of the upper arm and the forearm, which hold his arm's weight, and
the elbow's stiffness), its validation RMSE and the support levels the operator set. The export
copies his records (CSV per table, ``pilot.json``) and every file they index (``files/SESSION/``)
into a folder for a study's archive, with ``MANIFEST.sha256``; a file missing or changed since it
was recorded is not copied and is named in ``problems.txt``.

Both write into a staging folder beside the output and move their files into it when all are
written: an interrupted command leaves the output as it was. Design time only.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from daror_runtime.data.checksum import file_sha256
from daror_runtime.online.compare import verdict_text
from daror_runtime.records.measured import ElbowToday, MeasureError, elbow_today
from daror_runtime.records.pilots import load_pilot
from daror_runtime.records.schema import ModelRecord, RangeOfMotionRecord, SessionRecord
from daror_runtime.records.store import RecordsError, Store
from daror_runtime.util.atomic import atomic_path

#: The ISB angles of a range of motion, as the records' columns name them.
ISB_ANGLES = ("elevation", "horizontal_rotation", "axial_rotation", "elbow")


@dataclass(frozen=True)
class SessionTrend:
    """One session's point of the pilot's trend."""

    session_id: str
    started_utc: str | None
    final_state: str
    ended: str
    rom_deg: dict[str, tuple[float, float]] | None  # ISB angle -> (lower, upper)
    model_kind: str | None
    validation_rmse_nm: float | None
    validation_rmse_per_joint_nm: list[float] | None  # the elbow's (joint 4) rises first as his stiffness grows
    upper_arm_moment_nm: float | None  # |(theta3x, theta3y)|: the upper arm's first moment times g
    forearm_moment_nm: float | None  # |(theta4x, theta4y)|
    elbow_stiffness_nm_per_rad: float | None  # the elbow polynomial's mean slope over his elbow range
    support_levels: list[float] = field(default_factory=list)
    #: The elbow residual's slope on this session's own validation run under the model in use (Nm/rad):
    #: the stiffness his elbow gained since the model's data (daror_runtime.records.measured).
    elbow_gained_nm_per_rad: float | None = None
    #: The model's elbow stiffness plus what it gained: his elbow's stiffness today (Nm/rad).
    elbow_stiffness_today_nm_per_rad: float | None = None
    notes: list[str] = field(default_factory=list)  # why a measure is missing
    #: the online indicators per model that compensated (issue 29, docs/online.md), as the session kept them
    online: list[dict[str, Any]] = field(default_factory=list)
    comparison: dict[str, Any] | None = None  # a blind comparison's verdict (issue 29)


def _moment(parameters: dict[str, Any], link: int) -> float | None:
    names, values = parameters.get("theta_names"), parameters.get("theta")
    if not isinstance(names, list) or not isinstance(values, list) or len(names) != len(values):
        return None
    by_name = dict(zip(names, values, strict=True))
    x, y = by_name.get(f"theta{link}x"), by_name.get(f"theta{link}y")
    if x is None or y is None:
        return None
    return float(math.hypot(float(x), float(y)))


def _elbow_stiffness(parameters: dict[str, Any], elbow_deg: tuple[float, float] | None) -> float | None:
    """The elbow polynomial's mean slope (Nm/rad) over ``elbow_deg`` (his range; 10-110 deg without one)."""
    coefficients = parameters.get("elbow_polynomial")
    if not isinstance(coefficients, list) or not coefficients:
        return None
    lower, upper = np.deg2rad(elbow_deg if elbow_deg is not None else (10.0, 110.0))
    if upper <= lower:
        return None
    polynomial = np.polynomial.Polynomial([float(c) for c in coefficients])  # ascending powers of q4 (rad)
    return float((polynomial(upper) - polynomial(lower)) / (upper - lower))


def _rom(row: RangeOfMotionRecord | None) -> dict[str, tuple[float, float]] | None:
    if row is None:
        return None
    return {name: (getattr(row, f"{name}_lower_deg"), getattr(row, f"{name}_upper_deg")) for name in ISB_ANGLES}


def _elbow_today(session: SessionRecord, model: ModelRecord | None) -> ElbowToday | str:
    """What this session's own validation run measures of his elbow under ``model``, or why nothing."""
    if model is None:
        return "no model in use"
    # the stationary points, not the raw log beside them (NAME.raw.*), which the loader would reduce again
    runs = [d for d in session.datasets if d.run == "validation" and ".raw." not in Path(d.path).name]
    if not runs:
        return "no validation run in this session"
    run = runs[-1]
    try:
        return elbow_today(model.path, model.sha256, run.path, run.sha256)
    except MeasureError as error:
        return str(error)


def pilot_trend(store: Store, code: str) -> list[SessionTrend]:
    """The pilot's sessions, oldest first, as points of his trend.

    Raises:
        RecordsError: no pilot under ``code``.
    """
    with store.session() as orm:
        pilot = load_pilot(orm, code, store.url_shown)
        trend = []
        for s in pilot.sessions:
            rom = _rom(s.ranges_of_motion[-1] if s.ranges_of_motion else None)
            model = next((m for m in s.models if m.in_use), None)
            parameters = model.parameters if model is not None else {}
            stiffness = _elbow_stiffness(parameters, None if rom is None else rom["elbow"])
            today = _elbow_today(s, model)
            gained = today.slope_nm_per_rad if isinstance(today, ElbowToday) else None
            trend.append(
                SessionTrend(
                    session_id=s.session_id,
                    started_utc=None if s.started_utc is None else s.started_utc.isoformat(timespec="seconds"),
                    final_state=s.final_state,
                    ended="crashed" if s.ended_by_crash else (s.ended_reason or "not ended"),
                    rom_deg=rom,
                    model_kind=None if model is None else model.kind,
                    validation_rmse_nm=None if model is None else model.validation_rmse_nm,
                    validation_rmse_per_joint_nm=None if model is None else model.validation_rmse_per_joint_nm,
                    upper_arm_moment_nm=_moment(parameters, 3),
                    forearm_moment_nm=_moment(parameters, 4),
                    elbow_stiffness_nm_per_rad=stiffness,
                    support_levels=list(s.support_levels),
                    elbow_gained_nm_per_rad=gained,
                    elbow_stiffness_today_nm_per_rad=None
                    if gained is None or stiffness is None
                    else stiffness + gained,
                    notes=[] if isinstance(today, ElbowToday) else [f"elbow today: {today}"],
                    online=list(s.online or []),
                    comparison=s.comparison,
                )
            )
    return trend


def _markdown(code: str, trend: list[SessionTrend]) -> str:
    def number(value: float | None, digits: int = 3) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    lines = [
        f"# Pilot {code}: {len(trend)} session(s)",
        "",
        "Per session (oldest first): his range of motion (ISB angles, deg), the model in use, its",
        "validation RMSE, the first moments of the upper arm and the forearm (m g |p| in Nm: his arm's",
        "weight as the model holds it), the elbow's stiffness in the model (the elbow polynomial's mean",
        "slope over his elbow range, Nm/rad), what his elbow gained since the model's data (the slope of",
        "the elbow's residual against the elbow angle on the session's own validation run, Nm/rad) and",
        "the two added: his elbow's stiffness today, as long as his arm's weight did not change. A",
        "returning pilot's model is re-validated, not retrained: its own stiffness stays that of the",
        "session that trained it, and today's column follows him. Then the support levels set. The",
        "figure: report.png.",
        "",
        "| session | started (UTC) | ended | elevation | horizontal | axial | elbow | model | RMSE (Nm) | "
        "RMSE at the elbow (Nm) | upper arm (Nm) | forearm (Nm) | elbow stiffness, model (Nm/rad) | "
        "gained (Nm/rad) | elbow stiffness today (Nm/rad) | support |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for t in trend:
        rom = ["-"] * 4 if t.rom_deg is None else [f"{lo:g}..{hi:g}" for lo, hi in t.rom_deg.values()]
        lines.append(
            f"| {t.session_id} | {t.started_utc or '-'} | {t.ended} | {' | '.join(rom)} | {t.model_kind or '-'} | "
            f"{number(t.validation_rmse_nm)} | "
            f"{number(t.validation_rmse_per_joint_nm[3] if t.validation_rmse_per_joint_nm else None)} | "
            f"{number(t.upper_arm_moment_nm)} | {number(t.forearm_moment_nm)} | "
            f"{number(t.elbow_stiffness_nm_per_rad, 2)} | {number(t.elbow_gained_nm_per_rad, 2)} | "
            f"{number(t.elbow_stiffness_today_nm_per_rad, 2)} | {', '.join(f'{v:g}' for v in t.support_levels) or '-'} |"
        )
    online = [
        f"- {t.session_id}, {entry['model']}: {entry['rests']} rests, his effort at rest RMS "
        f"{' '.join('-' if v is None else f'{v:.2f}' for v in entry['effort_at_rest_rms_nm'] or [None] * 4)} Nm"
        + ("" if entry["level_delivered"] is None else f", support delivered {entry['level_delivered']:.2f}")
        for t in trend
        for entry in t.online
    ]
    if online:
        lines += ["", "Measured while he used the support (docs/online.md; against the model in use):", "", *online]
    compared = [f"- {t.session_id}: {verdict_text(t.comparison)}" for t in trend if t.comparison]
    if compared:
        lines += ["", "Blind comparisons (docs/online.md):", "", *compared]
    notes = [f"- {t.session_id}: {note}" for t in trend for note in t.notes]
    if notes:
        lines += ["", "Measures missing:", "", *notes]
    return "\n".join(lines) + "\n\n![his trend](report.png)\n"


def _figure(code: str, trend: list[SessionTrend], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.arange(1, len(trend) + 1)
    figure, axes = plt.subplots(2, 2, figsize=(11, 7), constrained_layout=True)
    rom_axis, moment_axis, stiffness_axis, fit_axis = axes.ravel()
    for name in ISB_ANGLES:
        lower = [np.nan if t.rom_deg is None else t.rom_deg[name][0] for t in trend]
        upper = [np.nan if t.rom_deg is None else t.rom_deg[name][1] for t in trend]
        line = rom_axis.plot(x, upper, marker="o", label=name.replace("_", " "))[0]
        rom_axis.plot(x, lower, marker="o", linestyle="--", color=line.get_color())
    rom_axis.set(title="range of motion (upper solid, lower dashed)", ylabel="deg")
    rom_axis.legend(fontsize=8)
    for attribute, label in (("upper_arm_moment_nm", "upper arm"), ("forearm_moment_nm", "forearm")):
        values = [np.nan if getattr(t, attribute) is None else getattr(t, attribute) for t in trend]
        moment_axis.plot(x, values, marker="o", label=label)
    moment_axis.set(title="first moments of the model in use (m g |p|)", ylabel="Nm")
    moment_axis.legend(fontsize=8)
    stiffness = [np.nan if t.elbow_stiffness_nm_per_rad is None else t.elbow_stiffness_nm_per_rad for t in trend]
    stiffness_axis.plot(x, stiffness, marker="o", linestyle="--", color="tab:red", label="in the model in use")
    today = [
        np.nan if t.elbow_stiffness_today_nm_per_rad is None else t.elbow_stiffness_today_nm_per_rad for t in trend
    ]
    stiffness_axis.plot(x, today, marker="D", color="tab:purple", label="today (his validation run)")
    stiffness_axis.set(title="elbow stiffness (mean slope over his elbow range)", ylabel="Nm/rad")
    stiffness_axis.legend(fontsize=8)
    rmse = [np.nan if t.validation_rmse_nm is None else t.validation_rmse_nm for t in trend]
    fit_axis.plot(x, rmse, marker="o", label="validation RMSE (Nm)")
    elbow = [np.nan if not t.validation_rmse_per_joint_nm else t.validation_rmse_per_joint_nm[3] for t in trend]
    fit_axis.plot(x, elbow, marker="^", linestyle=":", label="... at the elbow (Nm)")
    support = [max(t.support_levels) if t.support_levels else np.nan for t in trend]
    fit_axis.plot(x, support, marker="s", label="support level set (highest)")
    fit_axis.set(title="the model's fit and the support given")
    fit_axis.legend(fontsize=8)
    for axis in axes.ravel():
        axis.set_xlabel("session")
        axis.set_xticks(x)
        axis.grid(alpha=0.3)
    figure.suptitle(f"pilot {code}")
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100)
    plt.close(figure)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buffer.getvalue())


def _publish(staging: Path, out: Path) -> list[Path]:
    """Move every file of ``staging`` into ``out`` (created), each by an atomic rename; the staging goes."""
    out.mkdir(exist_ok=True)
    moved = []
    for item in sorted(staging.iterdir()):
        target = out / item.name
        if item.is_dir():
            if target.exists():
                shutil.rmtree(target)
            os.replace(item, target)
        else:
            os.replace(item, target)
        moved.append(target)
    staging.rmdir()
    return moved


def write_report(store: Store, code: str, out: Path | str) -> list[SessionTrend]:
    """Write the pilot's trend report into ``out`` (``report.md``, ``report.png``, ``report.json``).

    Raises:
        RecordsError: no pilot under ``code``, or no session of his.
    """
    trend = pilot_trend(store, code)
    if not trend:
        raise RecordsError(f"pilot {code}: no session in the records yet; nothing to report")
    out = Path(out)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent if str(out.parent) else "."))
    try:
        (staging / "report.md").write_text(_markdown(code, trend), encoding="utf-8")
        document = {"pilot": code, "sessions": [asdict(t) for t in trend]}
        (staging / "report.json").write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
        _figure(code, trend, staging / "report.png")
        _publish(staging, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return trend


@dataclass(frozen=True)
class Exported:
    """What :func:`export_pilot` wrote."""

    files: int
    problems: list[str]


def _csv(path: Path, rows: list[dict[str, Any]]) -> None:
    with path.open("w", newline="", encoding="utf-8") as handle:
        if not rows:
            return
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        for row in rows:
            writer.writerow({k: json.dumps(v) if isinstance(v, (list, dict)) else v for k, v in row.items()})


def _columns(record: Any) -> dict[str, Any]:
    row = {}
    for column in record.__table__.columns:
        value = getattr(record, column.key)
        row[column.key] = value.isoformat() if isinstance(value, datetime) else value
    return row


def export_pilot(store: Store, code: str, out: Path | str) -> Exported:
    """Copy the pilot's records and the files they index into ``out`` (a new folder).

    Raises:
        RecordsError: no pilot under ``code``, or ``out`` exists (an archive is never written over).
    """
    out = Path(out)
    if out.exists():
        raise RecordsError(f"{out}: exists; expected a new folder for the export (an archive is never written over)")
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent if str(out.parent) else "."))
    problems: list[str] = []
    manifest: list[str] = []
    try:
        with store.session() as orm:
            pilot = load_pilot(orm, code, store.url_shown)
            (staging / "pilot.json").write_text(json.dumps(_columns(pilot), indent=2) + "\n", encoding="utf-8")
            sessions = [_columns(s) for s in pilot.sessions]
            roms = [_columns(r) for s in pilot.sessions for r in s.ranges_of_motion]
            models = [_columns(m) for s in pilot.sessions for m in s.models]
            datasets = [_columns(d) for s in pilot.sessions for d in s.datasets]
            files: list[tuple[str, str, str | None]] = []  # (session id, path, sha256 recorded)
            for s in pilot.sessions:
                files.append((s.session_id, str(Path(s.directory) / "session.json"), None))
                files += [(s.session_id, m.path, m.sha256) for m in s.models]
                files += [(s.session_id, d.path, d.sha256) for d in s.datasets]
                files += [(s.session_id, r.path, r.sha256) for r in s.ranges_of_motion if r.path is not None]
        _csv(staging / "sessions.csv", sessions)
        _csv(staging / "ranges_of_motion.csv", roms)
        _csv(staging / "models.csv", models)
        _csv(staging / "datasets.csv", datasets)
        copied = 0
        for session_id, path, sha in files:
            source = Path(path)
            if not source.is_file():
                problems.append(f"{path}: missing (session {session_id})")
                continue
            actual = file_sha256(source)
            if sha is not None and actual != sha:
                problems.append(f"{path}: changed since it was recorded (session {session_id}); not copied")
                continue
            target = staging / "files" / session_id / source.name
            if target.exists():
                continue  # a model used in two sessions' folders is one file per session folder
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)
            manifest.append(f"{actual}  {target.relative_to(staging)}")
            copied += 1
        (staging / "MANIFEST.sha256").write_text("\n".join(manifest) + "\n", encoding="utf-8")
        if problems:
            (staging / "problems.txt").write_text("\n".join(problems) + "\n", encoding="utf-8")
        os.replace(staging, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return Exported(copied, problems)


__all__ = ["Exported", "SessionTrend", "export_pilot", "pilot_trend", "write_report"]
