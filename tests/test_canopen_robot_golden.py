"""The DAROR-01 robot file reproduces the behaviour before issue 25 bit for bit in lock-step HIL (D143).

``tests/data/daror01_golden.json`` holds one sha256 per stream (:mod:`tests.golden_streams`) of two
``daror hil`` runs of the demo session made with the code before the robot file existed (the short
form, commit 7f4f4f3): the whole session, and the session with an EMCY of drive 2 at 30 s. The same
runs with ``--hal-config examples/robot/daror01.yaml`` must give the same streams: every SYNC's
time and every RPDO and TPDO payload in bus order, every recorded array and dataset, the session's
end state and the audit log's events. Start-up's SDO and NMT frames and the heartbeats are not
compared (issue 25 added start-up steps and the heartbeat at NMT start).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.golden_streams import streams

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = json.loads((ROOT / "tests" / "data" / "daror01_golden.json").read_text(encoding="utf-8"))
ROBOT_FILE = ROOT / "examples" / "robot" / "daror01.yaml"
SCRIPT = ROOT / "daror_runtime" / "console" / "scripts" / "session.txt"


def _hil(out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "daror_runtime.cli", "hil", "--script", str(SCRIPT), "--out", str(out), *extra],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=1800,
        check=False,
    )


@pytest.mark.slow
@pytest.mark.parametrize("run", ["emcy_2_at_30", "session"])
def test_the_daror01_robot_file_reproduces_the_golden_run_bit_for_bit(tmp_path: Path, run: str) -> None:
    golden = GOLDEN["runs"][run]
    faults = [arg for fault in golden["faults"] for arg in ("--fault", fault)]
    done = _hil(tmp_path / "out", "--hal-config", str(ROBOT_FILE), *faults)
    assert "Traceback" not in done.stderr, done.stderr
    found = streams(tmp_path / "out")
    assert sorted(found) == sorted(golden["streams"])  # the same files and arrays were recorded
    drifted = sorted(name for name, sha in golden["streams"].items() if found[name] != sha)
    assert drifted == [], f"streams that differ from the golden run: {drifted}"
