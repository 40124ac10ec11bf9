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
from dataclasses import asdict, dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from daror_runtime.errors import DarorError, UsageError
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
    #: The 1, 5 and 15 min load averages (``os.getloadavg()``) when its benchmark started and when it
    #: ended: a figure measured while the other core was busy says so beside it (filled in by
    #: :func:`run_benchmarks` when the benchmark did not).
    load_start: tuple[float, float, float] | None = None
    load_end: tuple[float, float, float] | None = None

    @property
    def load(self) -> str:
        """The 1 min load average at the start and the end of the measurement, ``"0.71-1.02"``."""
        if self.load_start is None or self.load_end is None:
            return "-"
        return f"{self.load_start[0]:.2f}-{self.load_end[0]:.2f}"

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


_COMMAND_SCRIPT = """
import json, sys
from daror_runtime.bench import high_water_mark_mb
from daror_runtime.cli import main
code = main(sys.argv[2:])
with open(sys.argv[1], "w") as out:
    json.dump({"code": code, "peak_mb": high_water_mark_mb()}, out)
"""


@dataclass(frozen=True)
class CommandRun:
    """One ``daror`` command in a fresh interpreter: wall time start to exit (s), its own VmHWM (MB)."""

    wall_s: float
    peak_mb: float | None  # None: it died before reporting and was never seen running
    code: int | None  # the command's exit code; None when the process died before reporting it
    stderr: str


def command_in_child(
    argv: Sequence[str], workdir: Path, root: Path | None = None, memory_limit_mb: float | None = None
) -> CommandRun:
    """Run ``daror ARGV`` in a fresh interpreter in ``workdir``, as a user runs it, and measure it.

    ``root``: a source tree to measure instead of the installed one (the child's ``PYTHONPATH``);
    ``memory_limit_mb``: an address-space limit for the child. The child reports its own
    ``VmHWM`` at exit; while it runs its ``VmHWM`` is polled too, so a run that dies of the memory
    limit still has a figure.
    """
    import resource
    import subprocess
    import sys

    result = workdir / f".command-{os.getpid()}.json"
    result.unlink(missing_ok=True)
    log_path = workdir / f".command-{os.getpid()}.stderr"
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    if root is not None:
        env["PYTHONPATH"] = str(root)

    def limit() -> None:  # pragma: no cover - runs in the child
        if memory_limit_mb is not None:
            size = int(memory_limit_mb * 1024 * 1024)
            resource.setrlimit(resource.RLIMIT_AS, (size, size))

    start = time.perf_counter()
    with open(log_path, "w", encoding="utf-8") as errors:
        child = subprocess.Popen(
            [sys.executable, "-c", _COMMAND_SCRIPT, str(result), *argv],
            stdout=subprocess.DEVNULL,
            stderr=errors,
            env=env,
            cwd=workdir,  # not the source tree: '' comes first on sys.path
            preexec_fn=limit,
        )
        polled = 0.0
        while child.poll() is None:
            polled = max(polled, _child_high_water_mark_mb(child.pid))
            time.sleep(0.2)
    wall = time.perf_counter() - start
    stderr = log_path.read_text(encoding="utf-8", errors="replace")
    log_path.unlink(missing_ok=True)
    if not result.exists():
        return CommandRun(wall, polled or None, None, stderr)
    reported = json.loads(result.read_text())
    result.unlink()
    return CommandRun(wall, float(reported["peak_mb"]), int(reported["code"]), stderr)


def _child_high_water_mark_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as status:
            return next((int(line.split()[1]) / 1024 for line in status if line.startswith("VmHWM:")), 0.0)
    except OSError:
        return 0.0


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


def discover_by_script(directory: Path) -> dict[str, list[Benchmark]]:
    """The ``BENCHMARKS`` of every ``bench_*.py`` in ``directory``, by script name (``canopen`` for ``bench_canopen.py``).

    Raises:
        DarorError: a script cannot be loaded.
    """
    by_script: dict[str, list[Benchmark]] = {}
    for script in sorted(directory.glob("bench_*.py")):
        spec = importlib.util.spec_from_file_location(f"daror_bench_{script.stem}", script)
        if spec is None or spec.loader is None:
            raise DarorError(f"{script}: cannot load benchmark script")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        by_script[script.stem.removeprefix("bench_")] = list(getattr(module, "BENCHMARKS", []))
    return by_script


def discover(directory: Path) -> list[Benchmark]:
    """Every benchmark of the scripts in ``directory``, in script order (see :func:`discover_by_script`)."""
    return [b for benchmarks in discover_by_script(directory).values() for b in benchmarks]


def benchmark_list() -> str:
    """The benchmarks by script, one line each: the names ``daror bench --only`` matches a part of.

    Raises:
        DarorError: ``bench/`` is not there (an installed package) or a script cannot be loaded.
    """
    by_script = discover_by_script(bench_directory())
    return "\n".join(f"  {script}: {', '.join(b.__name__ for b in found)}" for script, found in by_script.items())


def run_benchmarks(
    console: Console, json_path: Path | None = None, quick: bool = False, only: str | None = None
) -> int:
    """Run every benchmark (or those whose function name contains ``only``) and report.

    Raises:
        UsageError: ``only`` is part of no benchmark's name (the message lists them; nothing runs).
        DarorError: the benchmark scripts cannot be found or loaded.
    """
    found = discover(bench_directory())
    selected: Sequence[Benchmark] = [b for b in found if only is None or only in b.__name__]
    if not selected:
        raise UsageError(
            f"--only {only!r} is part of no benchmark's name; expected part of one of: "
            + ", ".join(b.__name__ for b in found)
        )
    info = machine()
    console.print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, {info['date_utc']}")
    figures: list[BenchFigure] = []
    for bench in selected:
        console.print(f"  running {bench.__name__} ...")
        load_start = os.getloadavg()
        result = bench(quick)
        load_end = os.getloadavg()
        figures.extend(
            f if f.load_start is not None else replace(f, load_start=load_start, load_end=load_end)
            for f in (result if isinstance(result, list) else [result])
        )
    table = Table(title="Benchmarks (Load: the 1 min load average when the benchmark started and ended)")
    for header in ("Benchmark", "Median", "p90", "Target", "Met", "Load", "Thesis"):
        table.add_column(header, justify="left" if header in ("Benchmark", "Thesis") else "right")
    for f in figures:
        target = "-" if f.target is None else f"{'>=' if f.at_least else '<'} {f.target:g} {f.unit}"
        met = "-" if f.met is None else ("yes" if f.met else "NO")
        table.add_row(f.name, f"{f.median:.3g} {f.unit}", f"{f.p90:.3g} {f.unit}", target, met, f.load, f.thesis or "-")
    console.print(table)
    for f in figures:  # what a figure needs beside it (dropped rows, runs, counts)
        if f.note:
            console.print(f"  {f.name.strip()}: {f.note}", soft_wrap=True)
    if json_path is not None:
        document = {"machine": info, "quick": quick, "figures": [asdict(f) | {"met": f.met} for f in figures]}
        write_text_atomic(json_path, json.dumps(document, indent=2) + "\n")
        console.print(f"{json_path}: written")
    return 0
