"""Reading big data files (issue 10): load time and peak memory of 10^6 stationary rows, and whole commands.

* CSV, 10^6 rows of a stationary dataset (``t, q1..q4, tau1..tau4, dir1..dir4``, written by
  ``write_dataset``: 17 significant digits, about 185 MB): ``load_stationary`` in a fresh process.
  Targets: below 3 s and below 300 MB peak.
* ``.npz``, the same 10^6 rows: below 1 s.
* The whole ``daror fit plf+ --train BIG.csv`` and ``daror evaluate MODEL --data BIG.csv``,
  process start to exit.

Every figure comes from a child process (a fresh interpreter: no warm caches, no memory of an
earlier benchmark) that reads its own high-water mark, ``VmHWM`` in ``/proc/self/status``, at the
end; ``ru_maxrss`` of the parent would count a child it inherited. The note gives the high-water
mark right after the imports, so what the file itself cost is the difference. A child loads a
100-row file first, so numba's on-disk cache holds the compiled CSV parser (it compiles once per
installation, about 2 s).

Run directly, the script compares two source trees (e.g. the code before a change, extracted with
``git archive``): ``python bench/bench_data.py --root /tmp/daror_before``.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from daror_runtime.bench import BenchFigure
from daror_runtime.bench import command_in_child as run_command
from daror_runtime.data.load import write_dataset
from daror_runtime.data.schema import StationaryDataset

ROWS = 1_000_000
QUICK_ROWS = 100_000

_LOAD_SCRIPT = """
import json, sys, time
def hwm_mb():
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmHWM:")) / 1024
start = time.perf_counter()
from daror_runtime.data.load import load_stationary
imported = time.perf_counter()
baseline = hwm_mb()
data = load_stationary(sys.argv[1])
done = time.perf_counter()
print(json.dumps({"load_s": done - imported, "import_s": imported - start, "points": len(data),
                  "peak_mb": hwm_mb(), "baseline_mb": baseline}))
"""

_folder: list[Path] = []
_files: dict[tuple[int, str], Path] = {}


def folder() -> Path:
    """One temporary folder for the run's big files, removed when the process exits."""
    if not _folder:
        _folder.append(Path(tempfile.mkdtemp(prefix="daror-bench-data-")))
        atexit.register(shutil.rmtree, _folder[0], True)
    return _folder[0]


def big_stationary(n: int, seed: int = 10) -> StationaryDataset:
    """``n`` plausible stationary points: angles inside the joints' ranges, torques of a few Nm."""
    rng = np.random.default_rng(seed)
    low = np.array([-0.5, 0.0, -0.5, 0.2])
    high = np.array([1.5, 1.5, 1.0, 2.2])
    q = rng.uniform(low, high, (n, 4))
    tau = np.column_stack([np.sin(q[:, 0]), 6 * np.cos(q[:, 1]), 5 * np.sin(q[:, 2] + 1), 7 * np.sin(q[:, 3])])
    tau += rng.normal(0.0, 0.2, tau.shape)
    direction = rng.choice([-1.0, 0.0, 1.0], (n, 4))
    t = np.cumsum(rng.uniform(1.0, 3.0, n))
    return StationaryDataset(q, tau, direction, t)


def big_file(n: int, suffix: str) -> Path:
    """A file of ``n`` stationary rows (written once per run and format)."""
    key = (n, suffix)
    if key not in _files:
        path = folder() / f"big_{n}{suffix}"
        write_dataset(path, big_stationary(n))
        _files[key] = path
    return _files[key]


def _env(root: Path | None) -> dict[str, str]:
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    if root is not None:
        env["PYTHONPATH"] = str(root)
    return env


def load_in_child(path: Path, root: Path | None = None) -> dict[str, float]:
    """Load ``path`` with ``load_stationary`` in a fresh interpreter: seconds and VmHWM (MB)."""
    run = subprocess.run(
        [sys.executable, "-c", _LOAD_SCRIPT, str(path)],
        capture_output=True,
        text=True,
        env=_env(root),
        cwd=path.parent,  # not the source tree: '' comes first on sys.path
        check=False,
    )
    if run.returncode != 0:
        raise RuntimeError(f"loading {path} failed: {run.stderr.strip()[-2000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def command_in_child(argv: list[str], root: Path | None = None) -> dict[str, float]:
    """Run ``daror ARGV`` in a fresh interpreter: wall time from start to exit (s) and VmHWM (MB).

    Raises:
        RuntimeError: the command failed (its last error lines in the message).
    """
    run = run_command(argv, folder(), root)
    if run.code != 0 or run.peak_mb is None:
        raise RuntimeError(f"daror {' '.join(argv)}: exit code {run.code}: {run.stderr.strip()[-2000:]}")
    return {"wall_s": run.wall_s, "peak_mb": run.peak_mb}


def _load_figures(
    suffix: str, quick: bool, target_s: float, target_mb: float | None, root: Path | None = None
) -> list[BenchFigure]:
    n = QUICK_ROWS if quick else ROWS
    path = big_file(n, suffix)
    repeats = 1 if quick else 3
    load_in_child(big_file(100, suffix), root)  # numba's cache warm: the parser compiles once per install
    runs = [load_in_child(path, root) for _ in range(repeats)]
    seconds = [r["load_s"] for r in runs]
    peaks = [r["peak_mb"] for r in runs]
    size_mb = path.stat().st_size / 1e6
    note = (
        f"{n:,} rows, {size_mb:.0f} MB file; VmHWM after the imports {runs[0]['baseline_mb']:.0f} MB; "
        f"imports {runs[0]['import_s']:.2f} s"
    )
    label = f"load_stationary, {n:,}-row {suffix}"
    figures = [
        BenchFigure(
            f"{label}: time", float(np.median(seconds)), float(max(seconds)), "s", repeats, target_s, None, note
        )
    ]
    figures.append(
        BenchFigure(
            f"{label}: peak memory (VmHWM)", float(np.median(peaks)), float(max(peaks)), "MB", repeats, target_mb
        )
    )
    return figures


def bench_big_csv_load(quick: bool) -> list[BenchFigure]:
    """A 10^6-row stationary CSV read by ``load_stationary`` in a fresh process (10^5 with ``quick``)."""
    return _load_figures(".csv", quick, 3.0, 300.0)


def bench_big_npz_load(quick: bool) -> list[BenchFigure]:
    """The same rows as ``.npz``."""
    return _load_figures(".npz", quick, 1.0, None)


def _command_figures(quick: bool, root: Path | None = None) -> list[BenchFigure]:
    n = QUICK_ROWS if quick else ROWS
    path = big_file(n, ".csv")
    model = path.with_name("bench_model.json")
    fit = command_in_child(["fit", "plf+", "--train", str(path), "--out", str(model)], root)
    evaluate = command_in_child(["evaluate", str(model), "--data", str(path)], root)
    return [
        BenchFigure(f"daror fit plf+ --train ({n:,}-row CSV): start to exit", fit["wall_s"], fit["wall_s"], "s", 1),
        BenchFigure("  its peak memory (VmHWM)", fit["peak_mb"], fit["peak_mb"], "MB", 1),
        BenchFigure(
            f"daror evaluate MODEL --data ({n:,}-row CSV): start to exit",
            evaluate["wall_s"],
            evaluate["wall_s"],
            "s",
            1,
        ),
        BenchFigure("  its peak memory (VmHWM)", evaluate["peak_mb"], evaluate["peak_mb"], "MB", 1),
    ]


def bench_big_file_commands(quick: bool) -> list[BenchFigure]:
    """``daror fit plf+`` and ``daror evaluate`` on the 10^6-row CSV, process start to exit."""
    return _command_figures(quick)


BENCHMARKS = [bench_big_csv_load, bench_big_npz_load, bench_big_file_commands]


def _main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, help="source tree to measure (PYTHONPATH of the children)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--only", help="csv, npz or command")
    args = parser.parse_args()
    parts = {
        "csv": lambda: _load_figures(".csv", args.quick, 3.0, 300.0, args.root),
        "npz": lambda: _load_figures(".npz", args.quick, 1.0, None, args.root),
        "command": lambda: _command_figures(args.quick, args.root),
    }
    for name, part in parts.items():
        if args.only and args.only != name:
            continue
        for f in part():
            print(f"{f.name}: median {f.median:.3g} {f.unit}, max {f.p90:.3g} {f.unit}  {f.note}")


if __name__ == "__main__":
    _main()
