"""Render and write the protocol study: JSON, a plot of validation RMSE against robot time, Markdown.

Everything is rendered in memory first, then each file written atomically (JSON last), so a
failure while rendering leaves the output directory untouched (as the data-efficiency study).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from rich.table import Table

from daror_runtime.studies.protocol_study import DesignedRun, ProtocolStudyResult, RandomSubsets
from daror_runtime.studies.report_format import cell, png_bytes, write_study_files
from daror_runtime.util.outputs import OutputPathError

JSON_NAME = "protocol_study.json"
PNG_NAME = "protocol_study.png"
MARKDOWN_NAME = "protocol_study.md"

_COLOURS = {"both": "tab:green", "once": "tab:orange"}
_LABELS = {
    "both": "designed, every pose from both directions",
    "once": "designed, every pose once",
}


def output_paths(out_dir: Path | str) -> tuple[Path, Path, Path]:
    """The three files the study writes in ``out_dir``: JSON, PNG, Markdown."""
    folder = Path(out_dir)
    return folder / JSON_NAME, folder / PNG_NAME, folder / MARKDOWN_NAME


def _designed(result: ProtocolStudyResult, approach: str) -> list[DesignedRun]:
    return [d for d in result.designed if d.approach == approach and d.run is not None]


def _band(ax: object, subsets: tuple[RandomSubsets, ...], colour: str, label: str) -> None:
    usable = [s for s in subsets if s.summary.rmse_median is not None]
    if not usable:
        return
    x = np.array([s.mean_robot_time_s for s in usable])
    median = np.array([s.summary.rmse_median for s in usable], dtype=float)
    p5 = np.array([s.summary.rmse_p5 for s in usable], dtype=float)
    p95 = np.array([s.summary.rmse_p95 for s in usable], dtype=float)
    ax.fill_between(x, p5, p95, color=colour, alpha=0.15, linewidth=0)  # type: ignore[attr-defined]
    ax.plot(x, median, color=colour, marker="s", markersize=3, label=f"{label}: median, 5-95 %")  # type: ignore[attr-defined]


def render_png(result: ProtocolStudyResult, dpi: int = 120) -> bytes:
    """Validation RMSE (Nm) against robot time (s): designed protocols, random subsets, the full protocol."""
    figure = Figure(figsize=(8.0, 5.0), layout="constrained")
    FigureCanvasAgg(figure)
    ax = figure.subplots()
    full = result.full_rmse
    _band(ax, result.random_stops, "tab:red", "random stops of the full protocol, toured")
    _band(ax, result.random_points, "tab:blue", "random points of the full protocol (thesis, time pro rata)")
    for approach in ("both", "once"):
        runs = _designed(result, approach)
        if runs:
            x = [d.run.robot_time_s for d in runs if d.run is not None]
            y = [d.run.validation.rmse_nm for d in runs if d.run is not None and d.run.validation is not None]
            ax.plot(x, y, color=_COLOURS[approach], marker="o", linewidth=2, label=_LABELS[approach])
    ax.axhline(
        full,
        color="black",
        linestyle="--",
        linewidth=1,
        label=f"full protocol ({result.full.robot_time_s:.0f} s): {full:.4g} Nm",
    )
    ax.axhline(
        full * (1 + result.tolerance), color="grey", linestyle=":", linewidth=1, label=f"full + {result.tolerance:.0%}"
    )
    ax.set_ylim(full * 0.97, full * 1.25)
    ax.set_xlabel("robot time of the training run (s), approach and settle included")
    ax.set_ylabel("PLF+ validation RMSE (Nm)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title(
        f"{result.scenario}: PLF+ on one validation run ({result.validation.points} points); "
        f"{result.draws} random draws per budget",
        fontsize=9,
    )
    return png_bytes(figure, dpi)


def table_rows(result: ProtocolStudyResult) -> list[list[str]]:
    """One row per budget: designed (each approach), random stops, random points; RMSE in Nm."""
    rows = []
    for k, budget in enumerate(sorted({d.budget_s for d in result.designed})):
        row = [f"{budget:g}"]
        for approach in ("both", "once"):
            match = [d for d in result.designed if d.budget_s == budget and d.approach == approach]
            if not match:
                row.append("-")
            elif match[0].run is None or match[0].run.validation is None:
                row.append("refused")
            else:
                run = match[0].run
                row.append(f"{run.validation.rmse_nm:.4f} ({run.robot_time_s:.1f} s, {run.stops} stops)")
        stops, points = result.random_stops[k], result.random_points[k]
        row.append(
            f"{cell(stops.summary.rmse_median)} ({cell(stops.summary.rmse_p5)}-{cell(stops.summary.rmse_p95)}; "
            f"{stops.mean_stops or 0:.0f} stops)"
        )
        row.append(
            f"{cell(points.summary.rmse_median)} ({cell(points.summary.rmse_p5)}-{cell(points.summary.rmse_p95)}; n = {points.summary.n})"
        )
        rows.append(row)
    return rows


_HEADERS = (
    "budget (s)",
    "designed, both directions",
    "designed, once",
    "random stops, median (p5-p95)",
    "random points, median (p5-p95)",
)


def render_markdown(result: ProtocolStudyResult) -> str:
    """The study as Markdown: inputs, the table, the plot."""
    full = result.full
    lines = [
        f"# Designed identification protocols on {result.scenario} (issue 14)",
        "",
        f"- full training protocol: {full.robot_time_s:.1f} s of robot time, {full.stops} stops, {full.points} points; "
        f"PLF+ validation RMSE **{result.full_rmse:.4f} Nm**",
        f"- validation run: {result.validation.robot_time_s:.1f} s, {result.validation.points} points (every model is scored on it)",
        f"- random subsets: {result.draws} draws per budget, seed {result.seed}; within {result.tolerance:.0%} of the full protocol: "
        f"at most {result.full_rmse * (1 + result.tolerance):.4f} Nm",
        "",
        "PLF+ validation RMSE in Nm (Eq. 4.31). Designed: measured robot time of the closed-loop run and its data stops.",
        "",
        "| " + " | ".join(_HEADERS) + " |",
        "|" + "---:|" * len(_HEADERS),
    ]
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(result)]
    lines += ["", f"![validation RMSE against robot time]({PNG_NAME})", ""]
    return "\n".join(lines)


def summary_table(result: ProtocolStudyResult) -> Table:
    """The per-budget figures as a rich table for the console."""
    table = Table(title=f"{result.scenario}: PLF+ validation RMSE (Nm); full protocol {result.full_rmse:.4f} Nm")
    for header in _HEADERS:
        table.add_column(header, justify="right")
    for row in table_rows(result):
        table.add_row(*row)
    return table


def write_outputs(result: ProtocolStudyResult, out_dir: Path | str) -> tuple[Path, Path, Path]:
    """Write ``protocol_study.json``, ``.png`` and ``.md`` into ``out_dir`` (created if missing).

    Raises:
        OutputPathError: ``out_dir`` exists and is not a folder.
    """
    folder = Path(out_dir)
    if folder.exists() and not folder.is_dir():
        raise OutputPathError(f"{folder}: is a file; expected a folder")
    document = json.dumps(result.to_dict(), indent=2, allow_nan=False) + "\n"
    png = render_png(result)
    markdown = render_markdown(result)
    return write_study_files(folder, output_paths(folder), document, png, markdown)
