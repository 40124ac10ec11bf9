"""``daror hpsearch``: the hyper-parameter search of PENN and NNN, Tables I and II (docs/hpsearch.md)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import structlog
from rich.console import Console

from daror_runtime.cli.common import (
    TRUST_SIGNAL_MAP_HELP,
    Commands,
    UsageError,
    bind,
    output_dir,
    output_file,
    positive_int,
    progress,
)

log = structlog.get_logger(__name__)

#: The top-level modules of the optional extra ``nn`` that the search imports.
_NN_MODULES = ("jax", "jaxlib", "optax")


def register(commands: Commands) -> None:
    """``daror hpsearch`` on ``commands``."""
    hp = commands.add_parser(
        "hpsearch", help="hyper-parameter search of PENN and NNN: Tables I and II (thesis Sec. 4.2.5)"
    )
    hp.add_argument(
        "--train", type=Path, required=True, metavar="FILE", help="training data: stationary dataset or raw log"
    )
    hp.add_argument("--trust-signal-map", action="store_true", help=TRUST_SIGNAL_MAP_HELP)
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
        "--workers", type=positive_int, metavar="N", help="worker processes or local Ray CPUs (default: every core)"
    )
    hp.add_argument("--ray-address", metavar="A", help="with --executor ray: a running cluster (default: a local one)")
    hp.add_argument(
        "--cache-dir", type=Path, metavar="D", help="JAX's compilation cache (default $XDG_CACHE_HOME/daror/jax)"
    )
    hp.add_argument("--force", action="store_true", help="write into a folder that is not empty (replaces our files)")
    bind(hp, cmd_hpsearch)


def cmd_hpsearch(args: argparse.Namespace, console: Console) -> int:
    """The hyper-parameter search of PENN and NNN (docs/hpsearch.md): every check first, then the run, then the files."""
    from daror_runtime.bench import machine
    from daror_runtime.data.load import load_stationary_checked
    from daror_runtime.models.registry import ExtraNotInstalledError
    from daror_runtime.util.outputs import output_lock
    from hal.robot import load_description

    try:
        from daror_runtime.neural.compile_cache import default_cache_dir
        from daror_runtime.neural.hpsearch.executors import require_ray
        from daror_runtime.neural.hpsearch.grid import grid_from_argument
        from daror_runtime.neural.hpsearch.report import OUTPUT_NAMES, ranking, write_outputs
        from daror_runtime.neural.hpsearch.search import check_data, run_search
        from daror_runtime.neural.hpsearch.winner import fit_winners
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
    out = output_dir(args.out, args.train)
    if out.is_dir() and any(out.iterdir()) and not args.force:
        raise UsageError(
            f"{out}: the folder is not empty; the search writes {', '.join(OUTPUT_NAMES)} there: "
            "choose another --out, or give --force to replace them"
        )
    if out.is_dir():
        for name in OUTPUT_NAMES:
            output_file(out / name, args.train)
    data, signal_map = load_stationary_checked(
        args.train, load_description(None), trust_signal_map=args.trust_signal_map
    )
    note = signal_map.trust_note()
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
        with progress(
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
            winners = fit_winners(best, grid, data, args.train, out, load_description(None), note)
        paths = write_outputs(run, out, machine(), winners, note)
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
