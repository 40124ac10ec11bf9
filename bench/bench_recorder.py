"""Benchmarks of the crash-safe recorder (issue 3).

* ``push()`` of one 30-column row: it runs inside the 1 kHz tick; target below 5 us.
* Sustained throughput: 900,000 rows of 30 columns (15 minutes at 1 kHz) pushed as fast as the
  writer takes them, from ``start()`` to the end of ``close()`` (which fsyncs), in rows per
  second. A push the full block pool refuses is tried again after a short sleep (the benchmark
  is the producer, not a tick), so every row is written and the figure is the writer's rate,
  not the rate of rows thrown away; the note says how many pushes were refused.
* ``push()`` in a loop paced at 1 kHz (sleep to each deadline, like the real-time clock): after
  each sleep the caches are cold, so a push costs more than back to back; the figure's note gives
  a bare numpy row copy measured the same way, the floor any recorder has.
* Peak memory of the recorder over those 900,000 rows (tracemalloc, Python and numpy
  allocations), to show it is the block pool and does not grow with the run.
"""

from __future__ import annotations

import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np

from daror_runtime.bench import BenchFigure, time_calls
from daror_runtime.data.recorder import VALUE_BYTES, Recorder

N_COLUMNS = 30
N_ROWS_15_MIN = 900_000
COLUMNS = tuple(f"c{k}" for k in range(N_COLUMNS))


def _rows(n: int) -> np.ndarray:
    return np.random.default_rng(3).normal(size=(n, N_COLUMNS))


def bench_recorder_push_30_columns(quick: bool) -> BenchFigure:
    repeats = 20 if quick else 200
    rows = _rows(1000)
    state = {"i": 0}
    with tempfile.TemporaryDirectory() as directory, Recorder(Path(directory) / "push.rec", COLUMNS) as recorder:

        def one() -> None:
            state["i"] = (state["i"] + 1) % 1000
            recorder.push(rows[state["i"]])

        median, p90 = time_calls(one, repeats=repeats, per_call=1000, scale=1e6)
    note = f"ndarray row, back to back (hand-over amortised); {recorder.dropped_rows} of {recorder.rows_accepted + recorder.dropped_rows} rows dropped"
    return BenchFigure("recorder push(), 30 columns", median, p90, "us", repeats, 5.0, None, note)


def _paced_1khz_us(fn: Callable[[int], object], ticks: int) -> np.ndarray:
    """Duration of ``fn(tick)`` (us) in a loop that sleeps to a deadline every 1 ms."""
    durations = np.empty(ticks)
    deadline = time.perf_counter()
    for i in range(ticks):
        start = time.perf_counter()
        fn(i)
        durations[i] = time.perf_counter() - start
        deadline += 1e-3
        delay = deadline - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    return durations * 1e6


def bench_recorder_push_paced_1khz(quick: bool) -> BenchFigure:
    ticks = 1000 if quick else 5000
    rows = _rows(1000)
    plain = np.zeros_like(rows)

    def copy_row(i: int) -> None:
        plain[i % 1000] = rows[i % 1000]

    floor = _paced_1khz_us(copy_row, ticks)
    with tempfile.TemporaryDirectory() as directory, Recorder(Path(directory) / "paced.rec", COLUMNS) as recorder:
        pushes = _paced_1khz_us(lambda i: recorder.push(rows[i % 1000]), ticks)
    return BenchFigure(
        "recorder push(), 30 columns, paced 1 kHz",
        float(np.median(pushes)),
        float(np.percentile(pushes, 90)),
        "us",
        ticks,
        None,
        None,
        f"max {pushes.max():.0f} us; a bare numpy row copy paced the same: median {np.median(floor):.1f} us, "
        f"p90 {np.percentile(floor, 90):.1f} us, max {floor.max():.0f} us; {recorder.dropped_rows} rows dropped",
    )


def _record(path: Path, rows: np.ndarray, n_rows: int, wait_when_full: bool = False) -> Recorder:
    """``n_rows`` pushed back to back; with ``wait_when_full`` a refused row is pushed again until taken."""
    recorder = Recorder(path, COLUMNS)
    recorder.start()
    n_distinct = rows.shape[0]
    for i in range(n_rows):
        while not recorder.push(rows[i % n_distinct]) and wait_when_full:
            time.sleep(50e-6)
    recorder.close()
    return recorder


def bench_recorder_throughput_900k(quick: bool) -> BenchFigure:
    repeats = 1 if quick else 5
    rows = _rows(10_000)
    rates, refused = [], 0
    with tempfile.TemporaryDirectory() as directory:
        for k in range(repeats):
            path = Path(directory) / f"run{k}.rec"
            start = time.perf_counter()
            recorder = _record(path, rows, N_ROWS_15_MIN, wait_when_full=True)
            rates.append(recorder.rows_written / (time.perf_counter() - start))
            if recorder.rows_written != N_ROWS_15_MIN:
                raise RuntimeError(f"the recorder wrote {recorder.rows_written} of {N_ROWS_15_MIN} rows")
            refused += recorder.dropped_rows
            path.unlink()  # 216 MB each
    return BenchFigure(
        "recorder throughput, 900,000 x 30 rows",
        float(np.median(rates)),
        float(np.percentile(rates, 10)),  # the slow tail of a throughput is its low percentile
        "rows/s",
        repeats,
        None,
        None,
        f"start to close incl. fsync, every row written; p90 column is the 10th percentile; "
        f"{refused} pushes refused while the pool was full (tried again)",
    )


def bench_recorder_peak_memory_900k(quick: bool) -> BenchFigure:
    rows = _rows(10_000)
    with tempfile.TemporaryDirectory() as directory:
        tracemalloc.start()
        try:
            baseline = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            recorder = _record(Path(directory) / "memory.rec", rows, N_ROWS_15_MIN, wait_when_full=True)
            peak = tracemalloc.get_traced_memory()[1] - baseline
        finally:
            tracemalloc.stop()
    mib = peak / 2**20
    pool = recorder.capacity_rows * len(recorder.columns) * VALUE_BYTES / 2**20  # the blocks, allocated at start
    return BenchFigure(
        "recorder peak memory, 900,000 x 30 rows",
        mib,
        mib,
        "MiB",
        1,
        None,
        None,
        f"block pool {pool:.2f} MiB (64 blocks x 1000 rows); the file is {N_ROWS_15_MIN * N_COLUMNS * 8 / 2**20:.0f} MiB; "
        f"{recorder.rows_written:,} rows written; {recorder.dropped_rows} pushes refused while the pool was full "
        "(tried again)",
    )


BENCHMARKS = [
    bench_recorder_push_30_columns,
    bench_recorder_push_paced_1khz,
    bench_recorder_throughput_900k,
    bench_recorder_peak_memory_900k,
]
