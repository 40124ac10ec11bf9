"""Running a search: the grid cut into work units, scheduled most expensive first, on an executor.

:func:`run_search` is what ``daror hpsearch`` runs between checking its inputs and writing its
files (:mod:`.report`). The numbers do not depend on the executor, the number of workers or the
compilation cache: every unit is the same deterministic :func:`train_group` call wherever it runs.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.neural.hpsearch.executors import run_local, run_ray
from daror_runtime.neural.hpsearch.grid import SearchGrid
from daror_runtime.neural.hpsearch.work import NetworkRow, UnitResult, WorkerSetup, WorkUnit
from daror_runtime.neural.training import prepare_data

__all__ = ["SearchRun", "check_data", "run_search", "schedule", "work_units"]

#: ``on_progress(networks_done, networks_total, work_done)``: ``work_done`` is the fraction (0 to 1)
#: of the search's estimated cost (:meth:`WorkUnit.cost`) finished: the most expensive units run
#: first, so a bar of networks would fill slowly, then fast, and its time left would be wrong.
Progress = Callable[[int, int, float], None]


@dataclass(frozen=True)
class SearchRun:
    """A finished search.

    Attributes:
        grid: what was searched (its training's loss included).
        data_source: the training data's file; n_points: its points.
        data_rms_nm: RMS of the data's torque over every point and joint (Nm; collapse is judged
            against it).
        executor, workers: where it ran (``workers``: processes, or the local Ray instance's CPUs;
            0 for a Ray cluster that has its own).
        results: every unit, in the grid's order of shapes.
        wall_s: from the first unit handed out to the last result (s).
        started_utc: when it started (ISO 8601).
    """

    grid: SearchGrid
    data_source: str
    n_points: int
    data_rms_nm: float
    executor: str
    workers: int
    results: tuple[UnitResult, ...]
    wall_s: float
    started_utc: str

    @property
    def rows(self) -> list[NetworkRow]:
        """Every network, in the grid's order (shapes, then lambdas, then seeds)."""
        return [row for result in self.results for row in result.rows]

    @property
    def cpu_s(self) -> float:
        """CPU seconds of all units together (the workers' training, all threads)."""
        return float(sum(r.cpu_s for r in self.results))


def work_units(grid: SearchGrid) -> list[WorkUnit]:
    """One unit per shape of ``grid``, in the grid's order."""
    return [
        WorkUnit(index, spec, tuple(grid.l1), tuple(grid.seeds), grid.training)
        for index, spec in enumerate(grid.shapes())
    ]


def schedule(units: list[WorkUnit]) -> list[WorkUnit]:
    """``units`` most expensive first (:meth:`WorkUnit.cost`; ties in the grid's order)."""
    return sorted(units, key=lambda u: (-u.cost(), u.index))


def check_data(grid: SearchGrid, data: StationaryDataset) -> None:
    """Refuse data the grid's networks cannot be trained on, before any worker starts.

    Raises:
        DataError: a value that is not finite.
        IdentifiabilityError: too few points for the grid's validation folds.
    """
    prepare_data(grid.shapes()[0], data, grid.training)


def run_search(
    grid: SearchGrid,
    data: StationaryDataset,
    *,
    executor: str = "local",
    workers: int = 1,
    ray_address: str | None = None,
    cache_dir: Path | None = None,
    one_xla_thread: bool = True,
    on_progress: Progress | None = None,
) -> SearchRun:
    """Train every network of ``grid`` on ``data``.

    Args:
        executor: ``local`` (worker processes) or ``ray``.
        workers: local worker processes, or the CPUs of a local Ray instance.
        ray_address: a Ray cluster to run on (``ray`` only; None: a local instance).
        cache_dir: JAX's persistent compilation cache for the workers (None: none).
        one_xla_thread: keep each worker's XLA computations on one thread.
        on_progress: called after each unit with (networks done, networks in all, fraction of the
            estimated work done).

    Raises:
        DataError, IdentifiabilityError: see :func:`check_data`.
        WorkerDiedError: a worker died.
        ExtraNotInstalledError: ``ray`` without Ray installed.
        KeyboardInterrupt: Ctrl-C; the workers are ended first.
    """
    check_data(grid, data)
    units = schedule(work_units(grid))
    total = grid.n_networks
    total_cost = sum(u.cost() for u in units)
    setup = WorkerSetup(None if cache_dir is None else str(cache_dir), one_xla_thread)
    count, cost = [0], [0.0]

    def done(result: UnitResult) -> None:
        count[0] += result.unit.n_networks
        cost[0] += result.unit.cost()
        if on_progress is not None:
            on_progress(count[0], total, min(1.0, cost[0] / total_cost))

    started = datetime.now(UTC).isoformat(timespec="seconds")
    start = time.perf_counter()
    if executor == "local":
        results = run_local(units, data, setup, workers, done)
    elif executor == "ray":
        results = run_ray(units, data, setup, workers, ray_address, done)
    else:
        raise ValueError(f"executor {executor!r}: expected local or ray")
    wall = time.perf_counter() - start
    return SearchRun(
        grid=grid,
        data_source=data.source,
        n_points=len(data),
        data_rms_nm=float(np.sqrt(np.mean(np.asarray(data.tau_nm) ** 2))),
        executor=executor,
        workers=0 if executor == "ray" and ray_address is not None else workers,
        results=tuple(sorted(results, key=lambda r: r.unit.index)),
        wall_s=wall,
        started_utc=started,
    )
