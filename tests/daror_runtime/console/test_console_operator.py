"""Issue 9: the operator's console, as an operator uses it.

* An unguided operator, typing only what ``status`` suggests, takes the simulated pilot from
  start-up to compensation with the default settings: the path is ``tests/data/unguided_operator.txt``
  (every ``status`` followed by the commands it suggested), written by :func:`follow_the_status`
  (``python -m tests.daror_runtime.console.test_console_operator`` writes it again) and replayed here through the real
  command with the lines piped in, checking every line typed was suggested by the status before it.
* A person at a terminal (a pseudo-terminal): the prompt, completion, history across sessions,
  announcements printed apart from the prompt, and Ctrl-C or quit ending the session with torque
  off first and a line confirming it.
* Lines piped in: echoed, and the exit code says whether any failed.
* Quitting in any state removes torque, confirmed from the drives, and is recorded.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pexpect
import pytest
from rich.console import Console

from daror_runtime.console.run import make_session
from daror_runtime.console.view import NEXT_HEADING, suggested_commands
from daror_runtime.logs import configure_logging
from daror_runtime.runtime import Runtime
from hal.sim.backend import SimHal
from tests.conftest import Models
from tests.daror_runtime.session.test_session_safety import NAMES, Session

ROOT = Path(__file__).resolve().parents[3]
DAROR = Path(sys.executable).with_name("daror")
TRANSCRIPT = Path(__file__).parents[2] / "data" / "unguided_operator.txt"


# --- the unguided operator ----------------------------------------------------------------------


def follow_the_status(directory: Path, limit: int = 100) -> list[str]:
    """Type ``status``, then every command it suggests, until compensation; returns the lines typed.

    Default settings, the default scenario, lock-step: what ``daror console`` runs with lines piped in.
    """
    buffer = io.StringIO()
    runtime = Runtime(SimHal("exo_dummy_arm"), directory)
    runtime.open()
    typed: list[str] = []
    try:
        session = make_session(runtime, Console(file=buffer, width=200, highlight=False, color_system=None))
        for _ in range(limit):
            buffer.seek(0)
            buffer.truncate()
            session.execute("status")
            typed.append("status")
            if runtime.state_name == "compensation":
                return typed
            suggested = suggested_commands(buffer.getvalue())
            assert suggested, f"the status suggests nothing to do:\n{buffer.getvalue()}"
            for line in suggested:
                session.execute(line)
                typed.append(line)
    finally:
        runtime.shutdown("done")
        runtime.close()
    raise AssertionError(f"not in compensation after {limit} status views")


def _blocks(stdout: str) -> list[tuple[str, str]]:
    """(line typed, what it printed) for every echoed line of a piped session."""
    blocks: list[tuple[str, str]] = []
    for chunk in ("\n" + stdout).split("\n> ")[1:]:
        line, _, printed = chunk.partition("\n")
        blocks.append((line.strip(), printed))
    return blocks


@pytest.mark.subprocess
@pytest.mark.slow
def test_an_unguided_operator_reaches_compensation_with_the_default_settings(tmp_path: Path) -> None:
    typed = TRANSCRIPT.read_text(encoding="utf-8").splitlines()
    out = tmp_path / "session"
    run = subprocess.run(
        [str(DAROR), "console", "--out", str(out)],
        input="\n".join(typed) + "\n",
        capture_output=True,
        text=True,
        timeout=900,
        cwd=tmp_path,
        env={**os.environ, "COLUMNS": "200"},
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    blocks = _blocks(run.stdout)
    assert [line for line, _ in blocks] == typed  # every line was echoed, in order
    suggested: list[str] = []
    for line, printed in blocks:
        if line == "status":
            assert NEXT_HEADING in printed
            suggested = suggested_commands(printed)
            continue
        assert line in suggested, f"{line!r} was not suggested by the status before it: {suggested}"
        suggested = suggested[suggested.index(line) + 1 :]  # typed in the order suggested
    document = json.loads((out / "session.json").read_text(encoding="utf-8"))
    assert document["state"] == "compensation"
    assert document["model"]["validated"] is True
    assert document["faults"] == []
    assert document["ended"]["confirmed"] is True
    assert "torque off at t = " in run.stdout


# --- at a terminal --------------------------------------------------------------------------------


def _spawn(tmp_path: Path, out: Path) -> pexpect.spawn:
    env = {
        **os.environ,
        "XDG_STATE_HOME": str(tmp_path / "state"),  # the history file
        "PROMPT_TOOLKIT_NO_CPR": "1",  # pexpect's terminal does not answer cursor position requests
        "TERM": "xterm",
    }
    child = pexpect.spawn(
        str(DAROR), ["console", "--out", str(out)], env=env, encoding="utf-8", timeout=60, dimensions=(50, 160)
    )
    # Any prompt first, then its state: a console that starts in another state (a fault at start-up)
    # fails here with what it printed, not with a bare timeout.
    child.expect(r"\[(\w+)\] >")
    assert child.match.group(1) == "startup", f"the console started in {child.match.group(1)}: {child.before[-3000:]}"
    return child


def _session_json(out: Path) -> dict:
    return json.loads((out / "session.json").read_text(encoding="utf-8"))


@pytest.mark.subprocess
@pytest.mark.realtime
@pytest.mark.slow
def test_a_terminal_session_completes_remembers_announces_and_ends_with_torque_off_on_ctrl_c(tmp_path: Path) -> None:
    out = tmp_path / "first"
    child = _spawn(tmp_path, out)
    child.send("adv\t")  # completion
    child.expect("advance")
    child.send("\r")
    child.expect("advance: accepted, state safety_check")
    child.expect(r"\[safety_check\] >")
    child.send("sim estop operator on\r")
    child.expect("fault: estop: e-stop pressed \\(operator\\)")  # announced on its own line
    child.send("status\r")
    child.expect(NEXT_HEADING)
    child.expect("sim estop operator off")
    time.sleep(0.3)
    child.sendintr()  # Ctrl-C
    child.expect(r"torque off at t = [0-9.]+ s: every drive disabled \(state safety_check; interrupted")
    child.expect(pexpect.EOF)
    child.close()
    assert child.exitstatus == 130
    ended = _session_json(out)["ended"]
    assert ended["confirmed"] is True
    assert ended["reason"] == "interrupted by the operator (Ctrl-C)"
    assert ended["drives"] == ["disabled"] * 4
    audit = [json.loads(line) for line in (out / "audit.jsonl").read_text(encoding="utf-8").splitlines()]
    assert any(e["event"] == "session stopped: torque off" and e["torque_off_confirmed"] for e in audit)
    # a second session remembers what was typed in the first (history), and quit ends it the same way
    out2 = tmp_path / "second"
    child = _spawn(tmp_path, out2)
    child.send("\x1b[A")  # arrow up: the last line of the first session
    child.expect("status")
    child.send("\x15")  # Ctrl-U: clear the line
    child.send("quit\r")
    child.expect(r"torque off at t = [0-9.]+ s: every drive disabled \(state startup; quit\)")
    child.expect(pexpect.EOF)
    child.close()
    assert child.exitstatus == 0
    assert _session_json(out2)["ended"]["reason"] == "quit"


# --- lines piped in -------------------------------------------------------------------------------


@pytest.mark.subprocess
@pytest.mark.slow
def test_piped_lines_are_echoed_and_a_refusal_exits_1(tmp_path: Path) -> None:
    out = tmp_path / "session"
    run = subprocess.run(
        [str(DAROR), "console", "--out", str(out)],
        input="wait 0.2\nadvance\nadvance\n",  # the second advance: the e-stops are not tested
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 1, run.stderr
    assert [line for line, _ in _blocks(run.stdout)] == ["wait 0.2", "advance", "advance"]
    assert "refused (unmet: estop_operator_tested" in run.stdout
    assert "Traceback" not in run.stdout + run.stderr
    assert _session_json(out)["ended"]["reason"] == "quit or the end of the input"


# --- quitting in any state --------------------------------------------------------------------------


@pytest.fixture
def session(tmp_path: Path) -> Iterator[Session]:
    configure_logging("critical")
    s = Session(tmp_path / "session")
    yield s
    s.runtime.close()


@pytest.mark.slow
@pytest.mark.parametrize("state", [*NAMES, "FAIL"])
def test_quitting_in_any_state_takes_the_torque_off_first_and_records_it(
    session: Session, models: Models, state: str
) -> None:
    runtime = session.runtime
    if state in ("identification", "training", "compensation"):
        session.select(models.good, models.validation)
    if state == "FAIL":
        session.walk_to("rom_limits")
        session.hal.inject_fault("drive_fault", 2)
        runtime.runner.pass_time(0.01)
    else:
        session.walk_to(state)
    assert runtime.state_name == state
    ended = runtime.shutdown("quit")
    assert ended.confirmed
    assert ended.state == state
    assert ended.drives == ("disabled",) * 4 or (state == "FAIL" and "fault" in ended.drives)
    assert np.all(session.hal.applied_motor_torque_nm == 0.0)
    assert runtime.shutdown("again") is ended  # once only
    runtime.close()
    document = json.loads((runtime.session_dir / "session.json").read_text(encoding="utf-8"))
    assert document["ended"]["confirmed"] is True
    assert document["ended"]["state"] == state


if __name__ == "__main__":  # write the transcript again from what the status view suggests now
    import tempfile

    configure_logging("critical")
    with tempfile.TemporaryDirectory() as folder:
        lines = follow_the_status(Path(folder))
    TRANSCRIPT.parent.mkdir(exist_ok=True)
    TRANSCRIPT.write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"{TRANSCRIPT}: {len(lines)} lines")  # noqa: T201
