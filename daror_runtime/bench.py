"""``daror bench``: run the benchmark scripts under ``bench/`` and report their figures.

Each ``bench/bench_*.py`` exposes ``BENCHMARKS``, a list of callables ``(quick: bool) ->
BenchFigure``. Speed is measured here, never asserted in tests; the figures (with the machine and
the date) go to ``docs/performance.md``. Timing uses ``time.perf_counter`` over repeated runs and
reports the median and the 90th percentile, so one slow run (the other core busy) does not
decide the figure.
"""

from __future__ import annotations

import importlib.util
import json
import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from daror_runtime.errors import DarorError
from daror_runtime.util.atomic import write_text_atomic


@dataclass(frozen=True)
class BenchFigure:
    """One measured figure; ``target`` is an upper bound in ``unit`` (a lower bound when
    ``at_least``), None when there is no target."""

    name: str
    median: float
    p90: float
    unit: str
    repeats: int
    target: float | None = None
    thesis: str | None = None
    note: str = ""
    at_least: bool = False

    @property
    def met(self) -> bool | None:
        if self.target is None:
            return None
        return self.median >= self.target if self.at_least else self.median <= self.target


def time_each(call: Callable[[Any], object], items: Sequence[Any], repeats: int) -> tuple[float, float]:
    """Median and p90 (us) per call of ``call(item)``, cycling through ``items`` (1,000 calls a sample)."""
    state = {"i": 0}

    def one() -> None:
        state["i"] = (state["i"] + 1) % len(items)
        call(items[state["i"]])

    return time_calls(one, repeats=repeats, per_call=1000, scale=1e6)


def time_torque_one_q(model: Any, configurations: np.ndarray, quick: bool) -> tuple[float, float, int]:
    """Median and p90 (us) of ``model.torque(q)`` over rows of ``configurations``, and the repeats."""
    repeats = 20 if quick else 200
    median, p90 = time_each(model.torque, [np.asarray(q) for q in configurations[:1000]], repeats)
    return median, p90, repeats


def time_calls(fn: Callable[[], object], repeats: int, per_call: int = 1, scale: float = 1e3) -> tuple[float, float]:
    """Median and p90 of ``repeats`` timings of ``per_call`` calls each, per call, times ``scale``."""
    fn()  # warm-up: imports, caches, first-touch allocations
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(per_call):
            fn()
        samples.append((time.perf_counter() - start) / per_call * scale)
    return float(np.median(samples)), float(np.percentile(samples, 90))


def high_water_mark_mb() -> float:
    """This process's own peak resident memory, MB (``VmHWM``).

    Not ``ru_maxrss``: a child started by ``fork`` and ``exec`` reports the parent's peak there when
    the parent's was higher, so a small child read large (the old protocol figure was the parent's).
    """
    with open("/proc/self/status", encoding="ascii") as handle:
        for line in handle:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    raise DarorError("no VmHWM in /proc/self/status: peak memory cannot be read on this system")


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            cpu = next((line.split(":", 1)[1].strip() for line in handle if line.startswith("model name")), cpu)
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "system": f"{platform.system()} {platform.release()}",
        "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }


def bench_directory() -> Path:
    """``bench/`` of the source checkout this package runs from."""
    path = Path(__file__).resolve().parents[1] / "bench"
    if not path.is_dir():
        raise DarorError(f"{path}: benchmark scripts not found; run 'daror bench' from a source checkout")
    return path


Benchmark = Callable[[bool], "BenchFigure | list[BenchFigure]"]


def discover(directory: Path) -> list[Benchmark]:
    benchmarks: list[Benchmark] = []
    for script in sorted(directory.glob("bench_*.py")):
        spec = importlib.util.spec_from_file_location(f"daror_bench_{script.stem}", script)
        if spec is None or spec.loader is None:
            raise DarorError(f"{script}: cannot load benchmark script")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        benchmarks.extend(getattr(module, "BENCHMARKS", []))
    return benchmarks


def run_benchmarks(
    console: Console, json_path: Path | None = None, quick: bool = False, only: str | None = None
) -> int:
    """Run every benchmark (or those whose function name contains ``only``) and report."""
    selected: Sequence[Benchmark] = [b for b in discover(bench_directory()) if only is None or only in b.__name__]
    info = machine()
    console.print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, {info['date_utc']}")
    figures: list[BenchFigure] = []
    for bench in selected:
        console.print(f"  running {bench.__name__} ...")
        result = bench(quick)
        figures.extend(result if isinstance(result, list) else [result])
    table = Table(title="Benchmarks")
    for header in ("Benchmark", "Median", "p90", "Target", "Met", "Thesis"):
        table.add_column(header, justify="left" if header in ("Benchmark", "Thesis") else "right")
    for f in figures:
        target = "-" if f.target is None else f"{'>=' if f.at_least else '<'} {f.target:g} {f.unit}"
        met = "-" if f.met is None else ("yes" if f.met else "NO")
        table.add_row(f.name, f"{f.median:.3g} {f.unit}", f"{f.p90:.3g} {f.unit}", target, met, f.thesis or "-")
    console.print(table)
    for f in figures:  # what a figure needs beside it (dropped rows, runs, counts)
        if f.note:
            console.print(f"  {f.name.strip()}: {f.note}", soft_wrap=True)
    if json_path is not None:
        document = {"machine": info, "quick": quick, "figures": [asdict(f) | {"met": f.met} for f in figures]}
        write_text_atomic(json_path, json.dumps(document, indent=2) + "\n")
        console.print(f"{json_path}: written")
    return 0
