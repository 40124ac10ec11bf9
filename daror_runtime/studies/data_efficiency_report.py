"""Render and write the data-efficiency study: JSON, a Fig. 5.4-style plot, Markdown, a rich table.

Everything is rendered in memory first and only then written, each file atomically
(:mod:`daror_runtime.util.atomic`), so a failure while rendering leaves the output directory
untouched. The plot uses matplotlib's Agg canvas directly (no pyplot): no global figure state and
no display needed, so it works the same on the lab PC, over SSH and in CI.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from rich.table import Table

from daror_runtime.studies.data_efficiency import DataEfficiencyResult
from daror_runtime.studies.report_format import cell, png_bytes, write_study_files
from daror_runtime.util.outputs import OutputPathError

JSON_NAME = "data_efficiency.json"
PNG_NAME = "data_efficiency.png"
MARKDOWN_NAME = "data_efficiency.md"

#: Upper edge of the zoomed panel, as a multiple of the full-data RMSE: wide enough to show the
#: tolerance line and the approach to it, narrow enough that a 1 % difference is visible.
_ZOOM_TOP = 1.25


def output_paths(out_dir: Path | str) -> tuple[Path, Path, Path]:
    """The three files the study writes in ``out_dir``: JSON, PNG, Markdown."""
    folder = Path(out_dir)
    return folder / JSON_NAME, folder / PNG_NAME, folder / MARKDOWN_NAME


def _column(result: DataEfficiencyResult, name: str) -> np.ndarray:
    """One statistic over the sizes, NaN where a size has no fitted draw (matplotlib leaves a gap)."""
    values = [getattr(s, name) for s in result.sizes]
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _short(source: str) -> str:
    return Path(source).name or source


def _draw_panel(ax: Axes, result: DataEfficiencyResult, zoom: bool) -> None:
    n = np.array([s.n for s in result.sizes], dtype=float)
    mean = _column(result, "rmse_mean")
    std = _column(result, "rmse_std")
    p5, p95 = _column(result, "rmse_p5"), _column(result, "rmse_p95")
    full = result.full_data_rmse
    lower = mean - std
    if not zoom:
        # A log axis cannot show mean - std <= 0 (the spread at tiny n exceeds the mean); clip the
        # band at the smallest RMSE any draw reached, which is still an honest lower edge.
        floor = np.nanmin(_column(result, "rmse_min"))
        lower = np.maximum(lower, floor)
    ax.fill_between(n, p5, p95, color="tab:blue", alpha=0.15, linewidth=0, label="5th-95th percentile")
    ax.fill_between(n, lower, mean + std, color="tab:blue", alpha=0.30, linewidth=0, label="mean ± 1 std")
    ax.plot(n, mean, color="tab:blue", marker="o", markersize=3, label="mean validation RMSE")
    ax.axhline(
        full, color="black", linestyle="--", linewidth=1, label=f"all {result.train_points} points: {full:.4g} Nm"
    )
    if result.enough_points is not None:
        ax.axvline(
            result.enough_points,
            color="tab:green",
            linestyle=":",
            linewidth=1.2,
            label=f"enough: n = {result.enough_points} (mean within {result.tolerance:.0%})",
        )
    ax.set_xscale("log")
    ax.set_xlabel("training points n (random subset of the training set)")
    ax.set_ylabel("validation RMSE (Nm)")
    ax.grid(True, which="both", alpha=0.3)
    if zoom:
        limit = ax.axhline(
            full * (1.0 + result.tolerance),
            color="tab:green",
            linestyle="--",
            linewidth=0.8,
            alpha=0.7,
            label=f"full-data RMSE + {result.tolerance:.0%} (the enough-points limit)",
        )
        ax.legend(handles=[limit], fontsize=7, loc="upper right")
        ax.set_ylim(full * 0.95, full * _ZOOM_TOP)
        ax.set_title(f"zoom: within {(_ZOOM_TOP - 1.0):.0%} of the full-data RMSE", fontsize=9)
    else:
        ax.set_yscale("log")
        ax.set_title("all sizes (log scale)", fontsize=9)
        ax.legend(fontsize=7, loc="upper right")


def render_png(result: DataEfficiencyResult, dpi: int = 120) -> bytes:
    """The Fig. 5.4-style plot as PNG bytes: full range (log-log) above, a zoom near the full-data RMSE below."""
    figure = Figure(figsize=(8.0, 8.0), layout="constrained")
    FigureCanvasAgg(figure)  # attaches itself to the figure; Agg needs no display
    top, bottom = figure.subplots(2, 1)
    _draw_panel(top, result, zoom=False)
    _draw_panel(bottom, result, zoom=True)
    figure.suptitle(
        f"{result.display_name} data efficiency: train {_short(result.train_source)} "
        f"(N = {result.train_points}), validate {_short(result.validate_source)} "
        f"({result.validate_points} points), {result.draws} draws per size",
        fontsize=10,
    )
    return png_bytes(figure, dpi)


def render_markdown(result: DataEfficiencyResult) -> str:
    """A readable report: inputs, the rule for ``enough_points``, the per-size table and the plot."""
    enough = "none of the sizes studied" if result.enough_points is None else f"**n = {result.enough_points}**"
    share = (
        ""
        if result.enough_points is None
        else f" ({result.enough_points / result.train_points:.1%} of the training set)"
    )
    lines = [
        f"# Data efficiency of {result.display_name} (thesis Sec. 5.3.1, Fig. 5.4)",
        "",
        f"- training set: `{result.train_source}`, N = {result.train_points} stationary points",
        f"- validation set: `{result.validate_source}`, {result.validate_points} stationary points",
        f"- {result.draws} random subsets (without replacement) per size, seed {result.seed}",
        f"- full-data fit (all N points): validation RMSE {result.full_data.rmse_nm:.4g} Nm, "
        f"nRMSE {result.full_data.nrmse:.4g}",
        f"- enough points: {enough}{share}: the smallest n from which on every studied size has a mean "
        f"validation RMSE at most {1.0 + result.tolerance:g} x the full-data RMSE",
        "",
        "RMSE in Nm on the validation set (Eq. 4.31); nRMSE unitless (Eq. 4.32). *refused*: draws the "
        "fitter rejected as not identifiable, left out of the statistics.",
        "",
        "| n | fitted | refused | mean | std | min | p5 | median | p95 | max | mean nRMSE |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in result.sizes:
        lines.append(
            f"| {s.n} | {s.fitted} | {s.refused} | {cell(s.rmse_mean)} | {cell(s.rmse_std, 3)} | {cell(s.rmse_min)} "
            f"| {cell(s.rmse_p5)} | {cell(s.rmse_median)} | {cell(s.rmse_p95)} | {cell(s.rmse_max)} "
            f"| {cell(s.nrmse_mean)} |"
        )
    lines += ["", f"![validation RMSE against training points]({PNG_NAME})", ""]
    return "\n".join(lines)


def summary_table(result: DataEfficiencyResult) -> Table:
    """The per-size figures as a rich table for the console (RMSE in Nm)."""
    table = Table(
        title=(
            f"{result.display_name}: validation RMSE (Nm) on {_short(result.validate_source)} against training "
            f"points drawn from {_short(result.train_source)} (N = {result.train_points}), {result.draws} draws each"
        )
    )
    for column in ("n", "fitted", "refused", "mean", "std", "p5", "median", "p95", "max", "nRMSE"):
        table.add_column(column, justify="right")
    for s in result.sizes:
        style = "bold green" if s.n == result.enough_points else None
        table.add_row(
            str(s.n), str(s.fitted), str(s.refused), cell(s.rmse_mean), cell(s.rmse_std, 3), cell(s.rmse_p5),
            cell(s.rmse_median), cell(s.rmse_p95), cell(s.rmse_max), cell(s.nrmse_mean),
            style=style,
        )  # fmt: skip
    return table


def check_out_dir(out_dir: Path | str) -> None:
    """Refuse an output path that cannot become the study's directory, before any work is done.

    Raises:
        OutputPathError: ``out_dir`` exists and is not a folder (missing parents are created; the
            command line refuses them before it gets here, docs/decisions.md D61).
    """
    folder = Path(out_dir)
    if folder.exists() and not folder.is_dir():
        raise OutputPathError(f"{folder}: is a file; expected a folder")


def write_outputs(
    result: DataEfficiencyResult, out_dir: Path | str, signal_map_notes: tuple[str, ...] = ()
) -> tuple[Path, Path, Path]:
    """Write ``data_efficiency.json``, ``.png`` and ``.md`` into ``out_dir`` (created if missing).

    ``signal_map_notes``: what to say of data whose signal map failed and was trusted
    (``--trust-signal-map``): the JSON's ``signal_map`` and a line of the Markdown; nothing when empty.

    Returns:
        The paths written: JSON, PNG, Markdown.

    Raises:
        OutputPathError: ``out_dir`` exists and is not a folder.
    """
    folder = Path(out_dir)
    check_out_dir(folder)
    # Render everything before touching the disk: a rendering error must not leave a partial set.
    contents = result.to_dict()
    if signal_map_notes:
        contents["signal_map"] = list(signal_map_notes)
    document = json.dumps(contents, indent=2, allow_nan=False) + "\n"
    png = render_png(result)
    markdown = render_markdown(result) + "".join(f"\n**Signal map:** {note}\n" for note in signal_map_notes)
    return write_study_files(folder, output_paths(folder), document, png, markdown)
