"""Per-call costs of the parts of the 1 kHz tick that the identification protocol adds (issue 3).

The whole tick is measured in bench_loop.py; these isolate the pieces that run every tick.
"""

from __future__ import annotations

import numpy as np

from daror_runtime.bench import BenchFigure, time_calls, time_each
from daror_runtime.identification.trajectory_planning import build_trajectory
from daror_runtime.identification.waypoints import load_waypoints
from hal.isb import default_shoulder


def bench_isb_single(quick: bool) -> BenchFigure:
    shoulder = default_shoulder()
    q = shoulder.q_neutral.copy()
    repeats = 20 if quick else 100
    median, p90 = time_calls(lambda: shoulder.isb_single(q), repeats=repeats, per_call=1000, scale=1e6)
    return BenchFigure("ISB angles of one q (safety monitor, per tick)", median, p90, "us", repeats)


def bench_trajectory_reference(quick: bool) -> BenchFigure:
    training = build_trajectory(load_waypoints(), "training")
    times = np.arange(0.0, 60.0, 0.001).tolist()
    repeats = 20 if quick else 100
    median, p90 = time_each(training.reference, times, repeats)
    starts, coefficients = training.piecewise_table
    table_mb = (coefficients.nbytes + starts.nbytes + 2 * 32 * len(starts)) / 1e6  # arrays + the per-tick lists
    note = f"training: {training.duration_s / 60:.2f} min, {len(training.stops)} stops, {table_mb:.1f} MB"
    return BenchFigure("trajectory reference(t) (Python path)", median, p90, "us", repeats, note=note)


BENCHMARKS = [bench_isb_single, bench_trajectory_reference]
