"""Designing a short identification protocol (issue 14): target below 10 s for a 120 s protocol.

* ``design_protocol`` of a 120 s PLF+ protocol in the default ISB limits, every pose approached from
  both directions (the default) and once: candidates, D-optimal selection, tour, the built and
  checked trajectory. Warm (the process has designed once: numba's kernels loaded).
* ``daror protocol design --budget-s 120`` in a fresh process, start to exit (imports, numba's
  cache, the YAML written): what an operator waits for.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from daror_runtime.bench import BenchFigure, command_in_child, time_calls
from daror_runtime.identification.design import DesignSettings, design_protocol

BUDGET_S = 120.0


def bench_design_120s(quick: bool) -> list[BenchFigure]:
    repeats = 3 if quick else 10
    figures = []
    for approach in ("both", "once"):
        settings = DesignSettings(approach=approach)
        last = {}

        def design(settings: DesignSettings = settings, last: dict[str, object] = last) -> None:
            last["result"] = design_protocol(BUDGET_S, settings=settings)

        median, p90 = time_calls(design, repeats=repeats, scale=1.0)
        result = last["result"]
        prediction = result.protocol.prediction  # type: ignore[attr-defined]
        figures.append(
            BenchFigure(
                f"design a {BUDGET_S:g} s PLF+ protocol, approach {approach}",
                median,
                p90,
                "s",
                repeats,
                10.0,
                None,
                f"{prediction.poses} poses, {prediction.data_stops} stops, {prediction.robot_time_s:.1f} s of robot time "
                f"from {result.candidates} candidates",  # type: ignore[attr-defined]
            )
        )
    return figures


def bench_design_command(quick: bool) -> BenchFigure:
    repeats = 1 if quick else 3
    walls = []
    with tempfile.TemporaryDirectory() as folder:
        for k in range(repeats):
            out = Path(folder) / f"p{k}.yaml"
            run = command_in_child(
                ["protocol", "design", "--budget-s", f"{BUDGET_S:g}", "--out", str(out)], Path(folder)
            )
            if run.code != 0:
                raise RuntimeError(f"daror protocol design failed: {run.stderr}")
            walls.append(run.wall_s)
    walls.sort()
    return BenchFigure(
        "daror protocol design --budget-s 120, fresh process",
        walls[len(walls) // 2],
        walls[-1],
        "s",
        repeats,
        10.0,
        None,
        "start to exit: imports, numba cache, design, YAML",
    )


BENCHMARKS = [bench_design_120s, bench_design_command]
