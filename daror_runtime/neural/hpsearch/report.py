"""What a search writes: every network, the ranking of the configurations (Tables I and II), a summary.

Files in the output folder (:data:`OUTPUT_NAMES`):

* ``networks.csv``: one row per trained network (:class:`~.work.NetworkRow`'s fields), in the
  grid's order;
* ``ranking.csv``: one row per configuration (model, layers, width, activation, inputs, lambda),
  the best of its initialisations (lowest MVL, as the thesis keeps it; a NaN MVL never wins, ties go
  to the lower seed), ranked by MVL within its model (NaN last);
* ``ranking.md``: Table I (PENN) and Table II (NNN): the :data:`TOP` best configurations, with a
  header saying the data, the loss, the grid, the training and the machine time; the collapsed
  configurations; the most expensive shapes;
* ``summary.json``: the same facts for scripts, written last (its presence marks a complete set);
* ``best_penn.json``, ``best_nnn.json``: each searched model's winner fitted by ``daror fit`` (its
  command line in ranking.md and summary.json; :mod:`.winner`).

Every file is rendered in memory first, then written in two steps: all of them to temporary names
beside their targets (a failure here, a full disk, removes them: the folder is as it was), then
renamed into place one after the other (renames in one folder do not fail for want of space).
Ctrl-C is held from the first temporary file until the last rename, so the folder has all of this
run's files or none of them (and a folder the search created is removed again).
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import signal
import threading
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from daror_runtime.neural.fit import COLLAPSE_FRACTION
from daror_runtime.neural.hpsearch.search import SearchRun
from daror_runtime.neural.hpsearch.winner import WINNER_FILES, Winner
from daror_runtime.neural.hpsearch.work import NetworkRow
from daror_runtime.util.atomic import atomic_path

__all__ = [
    "OUTPUT_NAMES",
    "REPORT_NAMES",
    "TOP",
    "RankedConfiguration",
    "ranking",
    "render_markdown",
    "summary_document",
    "write_outputs",
]

#: Configurations per model in ranking.md's tables.
TOP = 10
#: Shapes listed in ranking.md and summary.json as the most expensive.
EXPENSIVE = 10
#: The report's files, summary.json last.
REPORT_NAMES = ("networks.csv", "ranking.csv", "ranking.md", "summary.json")
#: Every file a search may write: the winners' model files (of the models searched), then the report.
OUTPUT_NAMES = (*WINNER_FILES.values(), *REPORT_NAMES)
#: The version of summary.json's layout.
SUMMARY_VERSION = 1

_MODEL_ORDER = ("penn", "nnn")
_TABLE = {"penn": "Table I: PENN", "nnn": "Table II: NNN"}


@dataclass(frozen=True)
class RankedConfiguration:
    """One configuration (a shape and a lambda): its best initialisation and its rank within its model.

    Attributes:
        rank: 1 for the lowest MVL of its model.
        best: the network of the lowest MVL over the seeds.
        inits: initialisations trained.
        mvl_worst: the highest MVL over the seeds (NaN counts as highest), to show the spread.
    """

    rank: int
    best: NetworkRow
    inits: int
    mvl_worst: float


def _mvl_key(row: NetworkRow) -> tuple[bool, float]:
    finite = math.isfinite(row.mvl)
    return (not finite, row.mvl if finite else 0.0)


def ranking(rows: list[NetworkRow]) -> list[RankedConfiguration]:
    """The configurations of ``rows``, best initialisation each, ranked by MVL within each model (PENN first)."""
    groups: dict[tuple[Any, ...], list[NetworkRow]] = {}
    for row in rows:
        key = (row.model, row.layers, row.width, row.activation, row.inputs, row.l1)
        groups.setdefault(key, []).append(row)
    order = {key: i for i, key in enumerate(groups)}
    ranked: list[RankedConfiguration] = []
    for model in sorted({k[0] for k in groups}, key=_MODEL_ORDER.index):
        configs = []
        for key, members in groups.items():
            if key[0] != model:
                continue
            best = min(members, key=lambda r: (_mvl_key(r), r.seed))
            worst = max(members, key=_mvl_key)
            configs.append((best, len(members), worst.mvl if math.isfinite(worst.mvl) else math.nan, order[key]))
        configs.sort(key=lambda c: (_mvl_key(c[0]), c[3]))
        ranked.extend(RankedConfiguration(i + 1, b, n, w) for i, (b, n, w, _) in enumerate(configs))
    return ranked


def _number(value: float | int | bool | str) -> str:
    """A CSV cell: floats with every digit (``repr``), NaN and infinities as ``nan``/``inf``."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    return str(value)


def _csv(header: list[str], rows: list[list[Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows([[_number(v) for v in row] for row in rows])
    return buffer.getvalue()


def networks_csv(run: SearchRun) -> str:
    """``networks.csv``: every network, the fields of :class:`NetworkRow` in order."""
    names = [f.name for f in fields(NetworkRow)]
    return _csv(names, [[getattr(row, n) for n in names] for row in run.rows])


_RANK_COLUMNS = ("model", "layers", "width", "activation", "inputs", "l1", "mvl", "mvl_step", "val_rmse_nm")


def ranking_csv(ranked: list[RankedConfiguration]) -> str:
    """``ranking.csv``: rank within the model, the configuration, its best network, the spread over inits."""
    header = ["rank", *_RANK_COLUMNS, "seed", "collapsed", "inits", "mvl_worst_init"]
    rows = [
        [c.rank, *(getattr(c.best, n) for n in _RANK_COLUMNS), c.best.seed, c.best.collapsed, c.inits, c.mvl_worst]
        for c in ranked
    ]
    return _csv(header, rows)


def _loss_sentence(run: SearchRun) -> str:
    if run.grid.training.loss == "scaled":
        return (
            "**scaled** (the default): MVL is the mean over points and joints of the squared torque error "
            "divided by each joint's torque scale, dimensionless (a network of zero torque scores about 1), "
            "and the L1 penalty is lambda times the *mean* |weight|"
        )
    return (
        "**thesis** (Eq. 3.7): MVL is the mean squared torque error in Nm^2, and the L1 penalty is lambda "
        "times the *sum* of |weights|, with no scaling of inputs or outputs; at lambda 0.1 the penalty "
        "outweighs the error and drives a network to zero torque (collapsed)"
    )


def _training_sentence(run: SearchRun) -> str:
    s = run.grid.training
    optimiser = f"Adam {s.adam_steps} steps (learning rate {s.learning_rate:g})" + (
        f" then L-BFGS {s.lbfgs_steps} iterations" if s.lbfgs_steps else ""
    )
    held = ", ".join(str(b + 1) for b in s.held_out())
    return (
        f"{optimiser}, {s.steps} loss evaluations; {s.folds} contiguous blocks of time, block {held} held out; "
        f"per configuration the best of {len(run.grid.seeds)} initialisations (lowest MVL)"
    )


def _minutes(seconds: float) -> str:
    return f"{seconds:.1f} s" if seconds < 120 else f"{int(seconds // 60)} min {seconds % 60:.0f} s"


def _expensive(run: SearchRun) -> list[dict[str, Any]]:
    worst = sorted(run.results, key=lambda r: -r.wall_s)[:EXPENSIVE]
    return [
        {
            "shape": r.unit.spec.describe(),
            "networks": r.unit.n_networks,
            "wall_s": r.wall_s,
            "cpu_s": r.cpu_s,
            "compile_s": r.compile_s,
        }
        for r in worst
    ]


def _collapsed_lines(run: SearchRun, ranked: list[RankedConfiguration]) -> list[str]:
    lines = []
    for model in _MODEL_ORDER:
        configs = [c for c in ranked if c.best.model == model]
        if not configs:
            continue
        collapsed = [c for c in configs if c.best.collapsed]
        by_rate = ", ".join(
            f"lambda {rate:g}: {sum(c.best.l1 == rate for c in collapsed)} of {sum(c.best.l1 == rate for c in configs)}"
            for rate in run.grid.l1
        )
        lines.append(f"- {model.upper()}: {len(collapsed)} of {len(configs)} configurations collapsed ({by_rate})")
    return lines


def _winner_lines(winners: Sequence[Winner]) -> list[str]:
    """ranking.md's section on the winners' model files and the ``daror fit`` line of each."""
    if not winners:
        return []
    lines = [
        "",
        "## The winners as models",
        "",
        "Each model's best configuration, fitted by `daror fit` (its fold networks as the search trained them, "
        "then the fit on all the points); the line reproduces the file:",
    ]
    for w in winners:
        written = f"`{w.file_name}`" if w.file_name is not None else f"no file ({w.problem})"
        lines += ["", f"- {w.model.upper()}: {written}", "", "  ```sh", f"  {w.command}", "  ```"]
        lines += [f"  - differs from the search: {d}" for d in w.differences]
    return lines


def render_markdown(
    run: SearchRun, ranked: list[RankedConfiguration], machine: dict[str, Any], winners: Sequence[Winner] = ()
) -> str:
    """``ranking.md``: the header, Table I (PENN) and Table II (NNN), the winners' ``daror fit`` lines, collapses,
    the most expensive shapes."""
    unit = "" if run.grid.training.loss == "scaled" else " (Nm^2)"
    n = len(run.rows)
    out = [
        "# Hyper-parameter search (thesis Sec. 4.2.5, Tables I and II)",
        "",
        f"- **Data**: `{run.data_source}`, {run.n_points} stationary points, torque RMS {run.data_rms_nm:.4g} Nm",
        f"- **Loss**: {_loss_sentence(run)}",
        f"- **Grid**: {run.grid.describe()}",
        f"- **Training**: {_training_sentence(run)}",
        f"- **Machine time**: {n} networks in {_minutes(run.wall_s)} ({n / run.wall_s:.2f} networks/s), "
        f"{run.cpu_s:.0f} CPU s of training; executor {run.executor}"
        + (f", {run.workers} workers" if run.workers else "")
        + f"; {machine['cpu']}, {machine['cores']} cores; started {run.started_utc}",
        "",
        "MVL: minimal validation loss of the fold network on its held-out block. Validation RMSE: the RMSE "
        "(Nm, every joint of every point, Eq. 4.31) of that network at its MVL step on the held-out block. "
        f"Collapsed: its torque's RMS over the training points is below {COLLAPSE_FRACTION:.0%} of the data's.",
    ]
    for model in _MODEL_ORDER:
        configs = [c for c in ranked if c.best.model == model]
        if not configs:
            continue
        out += [
            "",
            f"## {_TABLE[model]}, the {min(TOP, len(configs))} best of {len(configs)} configurations",
            "",
            f"| rank | layers | width | activation | inputs | lambda | MVL{unit} | validation RMSE (Nm) | seed | collapsed |",
            "|---:|---:|---:|---|---|---:|---:|---:|---:|---|",
        ]
        for c in configs[:TOP]:
            b = c.best
            out.append(
                f"| {c.rank} | {b.layers} | {b.width} | {b.activation} | {b.inputs} | {b.l1:g} | {b.mvl:.5g} | "
                f"{b.val_rmse_nm:.4f} | {b.seed} | {'yes' if b.collapsed else 'no'} |"
            )
    out += _winner_lines(winners)
    out += ["", "## Collapsed configurations (zero torque: the network learned nothing)", ""]
    out += _collapsed_lines(run, ranked)
    out += ["", f"## The {EXPENSIVE} most expensive shapes (all their networks trained together)", ""]
    out += ["| shape | networks | wall s | CPU s | of which compiling s |", "|---|---:|---:|---:|---:|"]
    out += [
        f"| {e['shape']} | {e['networks']} | {e['wall_s']:.2f} | {e['cpu_s']:.2f} | {e['compile_s']:.2f} |"
        for e in _expensive(run)
    ]
    return "\n".join(out) + "\n"


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _configuration(c: RankedConfiguration) -> dict[str, Any]:
    row = {k: (_finite(v) if isinstance(v, float) else v) for k, v in asdict(c.best).items()}
    return {"rank": c.rank, **row, "inits": c.inits, "mvl_worst_init": _finite(c.mvl_worst)}


def summary_document(
    run: SearchRun, ranked: list[RankedConfiguration], machine: dict[str, Any], winners: Sequence[Winner] = ()
) -> dict[str, Any]:
    """``summary.json``: what was searched, on what, how long it took, the best configurations, collapses, the
    winners' model files and ``daror fit`` lines (:meth:`Winner.to_dict`)."""
    n = len(run.rows)
    models = [m for m in _MODEL_ORDER if m in run.grid.models]
    return {
        "version": SUMMARY_VERSION,
        "data": {"source": run.data_source, "points": run.n_points, "torque_rms_nm": run.data_rms_nm},
        "loss": run.grid.training.loss,
        "mvl_unit": "1" if run.grid.training.loss == "scaled" else "Nm^2",
        "grid": run.grid.model_dump(mode="json"),
        "networks": n,
        "configurations": len(ranked),
        "executor": run.executor,
        "workers": run.workers,
        "started_utc": run.started_utc,
        "wall_s": run.wall_s,
        "networks_per_s": n / run.wall_s if run.wall_s > 0 else None,
        "training_cpu_s": run.cpu_s,
        "machine": machine,
        "top": {m: [_configuration(c) for c in ranked if c.best.model == m][:TOP] for m in models},
        "collapsed_configurations": {m: sum(c.best.collapsed for c in ranked if c.best.model == m) for m in models},
        "most_expensive_shapes": _expensive(run),
        "winners": {w.model: w.to_dict() for w in winners},
        "files": _file_names(winners),
    }


def _file_names(winners: Sequence[Winner]) -> list[str]:
    """The files a search with ``winners`` writes, in the order they are listed (summary.json last)."""
    return [*(w.file_name for w in winners if w.file_name is not None), *REPORT_NAMES]


@contextlib.contextmanager
def _interrupt_held() -> Iterator[None]:
    """Hold Ctrl-C until the block is done, then raise it (main thread only; elsewhere no signal arrives)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


def write_outputs(
    run: SearchRun,
    out_dir: Path,
    machine: dict[str, Any],
    winners: Sequence[Winner] = (),
    signal_map_note: str | None = None,
) -> list[Path]:
    """Write the winners' model files and :data:`REPORT_NAMES` into ``out_dir`` (created if missing), all or none;
    the paths written, in order (summary.json last).

    ``signal_map_note``: the training file's signal map failed and was trusted: ``summary.json``'s
    ``signal_map`` says so (absent otherwise).

    Raises:
        OutputWriteError: the folder cannot be written (exit code 2); nothing was written.
        DarorError: writing failed otherwise (a full disk); nothing was written.
        ValueError: a winner's model file holds a number that is not finite; nothing was written.
    """
    ranked = ranking(run.rows)
    texts = {
        **{
            w.file_name: json.dumps(w.document, indent=2, allow_nan=False) + "\n"
            for w in winners
            if w.file_name is not None
        },
        "networks.csv": networks_csv(run),
        "ranking.csv": ranking_csv(ranked),
        "ranking.md": render_markdown(run, ranked, machine, winners),
        "summary.json": json.dumps(
            summary_document(run, ranked, machine, winners)
            | ({"signal_map": signal_map_note} if signal_map_note is not None else {}),
            indent=2,
            allow_nan=False,
        )
        + "\n",
    }
    created = not out_dir.exists()
    paths = [out_dir / name for name in _file_names(winners)]
    try:
        with _interrupt_held(), contextlib.ExitStack() as stack:
            # Each atomic_path renames its temporary file when the stack ends, last entered first:
            # entered in reverse, summary.json is renamed last. A failure before then removes every
            # temporary file and renames none.
            for path in reversed(paths):
                tmp = stack.enter_context(atomic_path(path))
                with open(tmp, "w", encoding="utf-8") as handle:
                    handle.write(texts[path.name])
                    handle.flush()
                    os.fsync(handle.fileno())  # a full disk shows here, before any rename, not at the rename
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                os.rmdir(out_dir)
        raise
    return paths
