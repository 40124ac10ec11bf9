"""The DAROR-01 robot file reproduces the behaviour before issue 25 bit for bit in lock-step HIL (D143).

``tests/data/daror01_golden.json`` holds one sha256 per stream (:mod:`tests.golden_streams`) of two
``daror hil`` runs of the demo session made with the code before the robot file existed (the short
form, commit 7f4f4f3, with ``--rate-hz 400``: the default rate since the worst cycle is budgeted, D160):
the session with the shorter identification of ``tests/data/hil_settings.yaml`` (every twelfth
waypoint, the Dummy Arm installed: ``--settings``, this checkout's file given to 7f4f4f3's code), and
the session with the built-in settings and an EMCY of drive 2 at 30 s. The same runs with ``--hal-config examples/robot/daror01.yaml``
must give the same streams: every SYNC's time and every RPDO and TPDO payload in bus order, every
recorded array and dataset, the session's end state and the audit log's events. Start-up's SDO and NMT
frames and the heartbeats are not compared (issue 25 added start-up steps and the heartbeat at NMT
start).

The session's golden was first the whole identification (584,087 SYNCs, 59 s of the suite's time),
then every third waypoint (259,272 SYNCs, 24 s, D193); every twelfth (52,389 SYNCs, 6 s, D200)
passes the same states with the same drives, mapping and lock-step, and still compares every PDO
frame of its run. It was made in a worktree of 7f4f4f3 (``git worktree add DIR 7f4f4f3``; in DIR:
``python -m daror_runtime.cli hil --script daror_runtime/console/scripts/session.txt --rate-hz 400 --settings
tests/data/hil_settings.yaml --out OUT``, then ``python -m tests.golden_streams OUT`` of this
checkout, with this checkout's ``tests/data/hil_settings.yaml`` copied into the worktree); the same
procedure without ``--settings`` gave the earlier whole-session golden bit for bit, and with every
third waypoint the golden of D193. The EMCY run ends 45 s into the session, before the
identification (at 73 s): it keeps the built-in settings, which the shorter ones would not shorten.

The second drive family (maxon EPOS4, ``examples/robot/epos4.yaml``), described by its vendor's EDS
and its robot file only, runs the same demo session on simulated drives built from that EDS and
ends as the DAROR-01's does: the same states in the same order, the model validated. It runs with the
shorter identification of ``tests/data/hil_settings.yaml`` (every twelfth waypoint), as its run on
durand's drives does (tests/hal/canopen/test_canopen_interop_lockstep.py): the drive family is what is tested,
and the whole identification took 100 s of the suite's time for nothing the shorter one misses.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.golden_streams import streams

ROOT = Path(__file__).resolve().parents[3]
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


@pytest.mark.subprocess
@pytest.mark.slow
@pytest.mark.parametrize("run", ["emcy_2_at_30", "session"])
def test_the_daror01_robot_file_reproduces_the_golden_run_bit_for_bit(tmp_path: Path, run: str) -> None:
    golden = GOLDEN["runs"][run]
    faults = [arg for fault in golden["faults"] for arg in ("--fault", fault)]
    settings = ["--settings", str(ROOT / golden["settings"])] if golden["settings"] is not None else []
    done = _hil(tmp_path / "out", "--hal-config", str(ROBOT_FILE), *faults, *settings)
    assert "Traceback" not in done.stderr, done.stderr
    found = streams(tmp_path / "out")
    assert sorted(found) == sorted(golden["streams"])  # the same files and arrays were recorded
    drifted = sorted(name for name, sha in golden["streams"].items() if found[name] != sha)
    assert drifted == [], f"streams that differ from the golden run: {drifted}"


#: The demo session's path through the FSM (the DAROR-01's golden run).
SESSION_PATH = [
    ("startup", "safety_check"),
    ("safety_check", "settings"),
    ("settings", "pilot_installation"),
    ("pilot_installation", "safety_experience"),
    ("safety_experience", "rom_limits"),
    ("rom_limits", "operative_check"),
    ("operative_check", "identification"),
    ("identification", "training"),
    ("training", "compensation"),
]


@pytest.mark.subprocess
@pytest.mark.slow
def test_the_epos4_family_runs_the_demo_session_as_the_daror01_does(tmp_path: Path) -> None:
    out = tmp_path / "out"
    settings = ROOT / "tests" / "data" / "hil_settings.yaml"
    done = _hil(out, "--hal-config", str(ROOT / "examples" / "robot" / "epos4.yaml"), "--settings", str(settings))
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    audit = [json.loads(line) for line in (out / "audit.jsonl").read_text(encoding="utf-8").splitlines()]
    assert [(e["source"], e["dest"]) for e in audit if e.get("event") == "transition"] == SESSION_PATH
    session = json.loads((out / "session.json").read_text(encoding="utf-8"))
    assert session["state"] == "compensation"
    assert session["faults"] == []
    assert session["model"]["validated"] is True
    bus = json.loads((out / "hil.json").read_text(encoding="utf-8"))["bus"]
    assert bus["rate_hz"] == 400.0  # its worst cycle fits the 70 % budget at 400 Hz (65.6 %), not at 500 Hz (82 %)
    assert bus["node_ids"] == [11, 12, 13, 14]
