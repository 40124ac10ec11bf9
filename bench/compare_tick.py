"""The session's tick in compensation on this checkout and on an older commit, alternating, in one run.

    .venv/bin/python bench/compare_tick.py 9ca195f [--rounds 3]

The older commit is checked out into a temporary git worktree (removed at the end); each round runs
one process per tree, this checkout's and the other's in turn, so that the VM's drift (docs/
performance.md) falls on both alike. Each process walks a lock-step session on ``exo_dummy_arm``
to compensation with a validated PLF+ model, the pilot limp with his arm raised, no fault
(``session_walk.py``, the same walk on both trees), and times ``ControlLoop.tick``: 40 blocks of
500 ticks, median, 10th and 90th percentile per tick (us). It checks that the session is still in
compensation without a fault after the timing, so both trees time the common path.

Exit codes: 0, 1 when a child failed (its stderr is shown), 2 for a commit git does not know.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

BENCH = Path(__file__).resolve().parent
CHECKOUT = BENCH.parent


def _child() -> None:
    """In a child process: the walk, then the timing, as one JSON line on stdout."""
    import time

    import numpy as np

    from daror_runtime.logs import configure_logging
    from daror_runtime.testing import session_core

    sys.path.insert(0, str(BENCH))
    from session_walk import session_in_compensation

    configure_logging("critical")
    with tempfile.TemporaryDirectory() as directory:
        runtime, _ = session_in_compensation(Path(directory))
        tick = session_core(runtime).loop.tick
        per_tick_us = []
        for _ in range(40):
            start = time.perf_counter_ns()
            for _ in range(500):
                tick()
            per_tick_us.append((time.perf_counter_ns() - start) / 500 / 1e3)
        state, faults = runtime.state_name, runtime.snapshot().faults
        runtime.close()
    if state != "compensation" or faults:
        raise SystemExit(f"the session left the common path: state {state}, faults {faults}")
    values = np.array(per_tick_us)
    print(json.dumps({"median": float(np.median(values)), "p10": float(np.percentile(values, 10)),
                      "p90": float(np.percentile(values, 90))}))  # fmt: skip


def _time(tree: Path) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(tree), "DAROR_COMPARE_CHILD": "1"}
    run = subprocess.run([sys.executable, __file__], env=env, capture_output=True, text=True, check=False)
    if run.returncode != 0:
        sys.stderr.write(run.stderr[-3000:])
        raise SystemExit(1)
    return dict(json.loads(run.stdout.strip().splitlines()[-1]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("commit", help="the older commit (anything git rev-parse takes)")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    resolved = subprocess.run(
        ["git", "-C", str(CHECKOUT), "rev-parse", "--verify", "--quiet", f"{args.commit}^{{commit}}"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    if resolved.returncode != 0:
        sys.stderr.write(f"compare_tick: {args.commit!r}: not a commit of {CHECKOUT}\n")
        return 2
    commit = resolved.stdout.strip()
    with tempfile.TemporaryDirectory() as scratch:
        other = Path(scratch) / "other"
        subprocess.run(
            ["git", "-C", str(CHECKOUT), "worktree", "add", "--detach", "-q", str(other), commit], check=True
        )
        try:
            print(f"load average at start: {os.getloadavg()[0]:.2f}")
            for n in range(1, args.rounds + 1):
                before, after = _time(other), _time(CHECKOUT)
                print(
                    f"round {n}: {commit[:7]} {before['median']:.2f} us (p10 {before['p10']:.2f}, p90 {before['p90']:.2f}); "
                    f"this checkout {after['median']:.2f} us (p10 {after['p10']:.2f}, p90 {after['p90']:.2f})"
                )
            print(f"load average at end: {os.getloadavg()[0]:.2f}")
        finally:
            subprocess.run(["git", "-C", str(CHECKOUT), "worktree", "remove", "--force", str(other)], check=False)
    return 0


if __name__ == "__main__":
    if os.environ.get("DAROR_COMPARE_CHILD") == "1":
        _child()
    else:
        sys.exit(main())
