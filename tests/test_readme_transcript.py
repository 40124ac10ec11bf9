"""Issue 24: a new user's transcript, the README's command list run in order, as its reader would.

Each ``daror`` line of the README's command block runs in a fresh folder (the checkout's paths made
absolute), as the README writes it; what it promises is checked: exit code 0 (the HIL example with
an injected fault exits 1, as its comment says, and still writes every file), no traceback, no fault
in a session the user did not cause, the files the comments name. A line this test cannot run
(hardware, the whole benchmark suite) is listed in :data:`NOT_RUN` with the reason; a README line
that is neither run nor listed fails the test, so the list cannot drift from the README.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from daror_runtime.records.store import HEAD_REVISION

ROOT = Path(__file__).resolve().parents[1]
DAROR = [sys.executable, "-m", "daror_runtime.cli"]

#: README lines not run here, and why (a line is named by its start).
NOT_RUN = {
    "daror console --hal-config robot.yaml": "drives the lab's robot over a real CAN interface",
    "daror can scan --hal-config robot.yaml": "the lab's robot file on a real CAN interface "
    "(tests/daror_runtime/commissioning/test_can_commissioning_scan.py runs it on simulated drives)",
    "daror can check --hal-config robot.yaml --yes-no-pilot": "enables the lab's robot's drives "
    "(tests/daror_runtime/commissioning/test_can_commissioning_check.py runs it on simulated drives)",
    "daror can zero --hal-config robot.yaml --at-zero-pose": "writes the lab's robot file "
    "(tests/daror_runtime/commissioning/test_can_commissioning_calibration.py runs it on simulated drives)",
    "daror hil --hal-config examples/robot/epos4.yaml --script daror_runtime/console/scripts/session.txt --out hil2": "the whole demo session on the EPOS4 family, about a minute and a half "
    "(tests/hal/canopen/test_canopen_robot_golden.py runs it with the shorter identification of tests/data/hil_settings.yaml; "
    "tests/hal/canopen/test_canopen_interop_lockstep.py on durand's drives)",
    "daror bench": "runs every benchmark (many minutes; docs/performance.md has their figures)",
    "daror rt-check --hal-config robot.yaml": "the lab's robot file; its verdict (exit 0 or 1) is the machine's "
    "(tests/daror_runtime/test_rt_check.py runs the command for 1 s)",
}


def readme_commands() -> list[str]:
    """The ``daror`` lines of the README's command block, without their comments."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    start = text.index("## The `daror` command")
    block = text[start:].split("```sh\n", 1)[1].split("```", 1)[0]
    return [line.split("  #", 1)[0].strip() for line in block.splitlines() if line.startswith("daror")]


@dataclass
class Ran:
    line: str
    returncode: int
    output: str


def _argv(line: str) -> list[str]:
    words = []
    for word in shlex.split(line)[1:]:
        for prefix in ("daror_runtime/", "examples/"):
            if word.startswith(prefix):
                word = str(ROOT / word)
        words.append(word)
    return DAROR + words


def _run(line: str, folder: Path, stdin: str = "") -> Ran:
    run = subprocess.run(
        _argv(line), cwd=folder, input=stdin, capture_output=True, text=True, timeout=900, check=False,
        env={**{k: v for k, v in os.environ.items() if k != "DAROR_DB"}, "COLUMNS": "200"},  # the reader's default records
    )  # fmt: skip
    return Ran(line, run.returncode, run.stdout + run.stderr)


def _web(line: str, folder: Path, out: str) -> Ran:
    """Start the web console (on a free port), read the address it prints, then Ctrl-C it as its user would."""
    process = subprocess.Popen(
        [*_argv(line), "--port", "0", "--out", out], cwd=folder, stdin=subprocess.PIPE,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    assert process.stdout is not None
    seen = []
    for text in process.stdout:
        seen.append(text)
        if "web console: http" in text:
            break
    time.sleep(1.0)
    process.send_signal(signal.SIGINT)
    rest, _ = process.communicate(timeout=60)
    return Ran(line, process.returncode, "".join(seen) + rest)


def _session(folder: Path, name: str) -> dict[str, object]:
    return json.loads((folder / name / "session.json").read_text(encoding="utf-8"))


def _size_as_said(folder: Path, line_start: str) -> None:
    """The folder's size is what the README's comment on that line says (``~126 MB``), within 15 %."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    comment = next(line for line in text.splitlines() if line.startswith(line_start)).split("#", 1)[1]
    said_mb = float(re.search(r"~(\d+) MB", comment).group(1))  # type: ignore[union-attr]
    size_mb = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 1e6
    assert abs(size_mb - said_mb) <= 0.15 * said_mb, f"{folder.name}: {size_mb:.0f} MB, the README says ~{said_mb:g} MB"


def _no_faults(folder: Path, name: str) -> None:
    session = _session(folder, name)
    assert session["faults"] == [], session["faults"]
    assert session["state"] != "FAIL"


#: What a line's comment promises, checked after it ran (by the line's start).
CHECKS: dict[str, Callable[[Ran, Path], None]] = {
    "daror simulate static --scenario exo_dummy_arm --trajectory training": lambda r, d: None,
    "daror hpsearch": lambda r, d: (
        (d / "search_B" / "best_penn.json").is_file() or pytest.fail("no best_penn.json"),
        "daror fit penn" in r.output or pytest.fail("no fit line for the best PENN"),
    ),
    "daror evaluate": lambda r, d: [
        m["training_range"] is not None or pytest.fail(m["name"])
        for m in json.loads((d / "errors.json").read_text(encoding="utf-8"))["models"]
        if m["kind"] != "ap"
    ],
    "daror identify --scenario exo_dummy_arm --dummy-arm --trajectory training": lambda r, d: (
        (d / "B_id.raw.npz").is_file() or pytest.fail("no raw log beside B_id.npz")
    ),
    "daror console --script": lambda r, d: (
        _no_faults(d, "session1"),
        _session(d, "session1")["state"] == "compensation" or pytest.fail("the script did not reach compensation"),
        _size_as_said(d / "session1", "daror console --script"),
    ),
    "daror hil": lambda r, d: (
        r.returncode == 1 or pytest.fail(f"exit {r.returncode}"),
        (d / "hil1" / "can.log.gz").is_file() or pytest.fail("no bus log"),
        json.loads((d / "hil1" / "hil.json").read_text(encoding="utf-8"))["faults"] or pytest.fail("no fault"),
    ),
    # the bare `daror console` above recorded itself into daror.db beside its folder (sessions/)
    "daror pilots list": lambda r, d: (
        "sim-exo_dummy_arm (simulated)" in r.output or pytest.fail("the console session's pilot is not listed"),
    ),
    # ... and so did `daror console --hal can-sim` (both in sessions/, their default folder)
    "daror sessions list": lambda r, d: (
        "2 session(s)" in r.output or pytest.fail(r.output),
        r.output.count("sim-exo_dummy_arm") == 2 or pytest.fail(r.output),
    ),
    "daror db upgrade": lambda r, d: f"schema {HEAD_REVISION} -> {HEAD_REVISION}" in r.output or pytest.fail(r.output),
    "daror console --web": lambda r, d: (
        r.returncode == 130 or pytest.fail(f"Ctrl-C: exit {r.returncode}"),
        "?token=" in r.output or "--no-token" in r.line or pytest.fail("no token in the printed address"),
        "torque off at t =" in r.output or pytest.fail("no torque off line"),
    ),
}


@pytest.mark.subprocess
@pytest.mark.slow
def test_the_readme_s_commands_in_order(tmp_path: Path) -> None:
    (tmp_path / "lines.txt").write_text("status\nadvance\nwait 0.5\nstatus\nquit\n", encoding="utf-8")
    ran: list[Ran] = []
    skipped: list[str] = []
    for line in readme_commands():
        if any(line.startswith(prefix) and line.split() == prefix.split() for prefix in NOT_RUN):
            skipped.append(line)
            continue
        if "--web" in line:
            result = _web(line, tmp_path, f"web{len(ran)}")
        elif "< lines.txt" in line:
            result = _run(line.replace(" < lines.txt", ""), tmp_path, (tmp_path / "lines.txt").read_text())
        elif line.endswith("console ..."):  # the audit's example: any console line; the bare one here
            result = _run(line.replace(" ...", " --out session3"), tmp_path)
        else:
            result = _run(line, tmp_path)
        ran.append(result)
        assert "Traceback" not in result.output, f"{line}\n{result.output[-3000:]}"
        if not line.startswith("daror hil") and " --web" not in line:
            assert result.returncode == 0, f"{line}: exit {result.returncode}\n{result.output[-3000:]}"
        for prefix, check in CHECKS.items():
            if line.startswith(prefix):
                check(result, tmp_path)
    assert sorted(skipped) == sorted(NOT_RUN), skipped
    for name in ("session2", "session3"):
        _no_faults(tmp_path, name)
    assert (tmp_path / "audit.jsonl").is_file()  # --log-json's file, and the session's own
    assert (tmp_path / "session3" / "audit.jsonl").is_file()
    assert len(ran) + len(skipped) == len(readme_commands())
