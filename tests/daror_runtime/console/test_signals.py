"""Issue 24, defect 4: SIGTERM and SIGHUP end a console session like Ctrl-C, in every mode and state.

``kill -TERM`` of ``daror console`` (any mode) ended the process with no torque off, no line, no
``session.json``. Now SIGINT, SIGTERM and SIGHUP take the same path (``console/run.py:
run_session``): the torque off from a fresh sample, the line saying so, the audit's
``session stopped: torque off`` and ``session.json``'s ``ended`` naming the signal, exit code 128 +
the signal's number.

* In-process: each signal in each state whose mode applies torque, and in FAIL while a fault's
  reaction holds the arm (D122: a signal is no operator's considered choice), sent by another thread
  while the main thread runs lock-step ticks (so it lands inside a tick), through the very function
  the command ends its sessions with.
* Real processes, one per mode, in a state that drives the arm: the prompt at a pseudo-terminal
  (SIGTERM, and the terminal closed: the kernel's hang-up), a script (SIGHUP), lines piped in
  (SIGTERM), ``daror hil`` (SIGTERM); the web console's in ``tests/daror_runtime/console/test_web_console.py``.
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pexpect
import pytest
from rich.console import Console

from daror_runtime.console.run import STOP_SIGNALS, run_session
from daror_runtime.fsm.modes import MODES
from daror_runtime.fsm.spec import load_fsm_spec
from daror_runtime.logs import configure_logging, flush_logs
from hal.interface import DriveState
from tests.conftest import Models
from tests.daror_runtime.session.test_session_safety import Session

DAROR = Path(sys.executable).with_name("daror")
SPEC = load_fsm_spec()
#: The states whose mode drives the motors (fsm_spec.yaml, daror_runtime/fsm/modes.py).
TORQUE_STATES = [state.name for state in SPEC.states if MODES[state.mode].applies_torque]
SIGNALS = {"SIGTERM": signal.SIGTERM, "SIGHUP": signal.SIGHUP}
ISB_LIMITS = (
    "elevation: {lower_deg: 0, upper_deg: 100}\nhorizontal_rotation: {lower_deg: -20, upper_deg: 165}\n"
    "axial_rotation: {lower_deg: -75, upper_deg: 75}\nelbow: {lower_deg: 5, upper_deg: 120}\n"
)


def _audit(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def _check_ended(out: Path, audit: Path, signum: int, state: str | None = None) -> dict[str, Any]:
    """session.json and the audit: the torque off confirmed, every drive read back disabled, the signal named."""
    ended = json.loads((out / "session.json").read_text(encoding="utf-8"))["ended"]
    assert ended["reason"] == STOP_SIGNALS[signum]
    assert ended["confirmed"] is True
    assert ended["drives"] == ["disabled"] * 4
    assert ended["error"] is None
    if state is not None:
        assert ended["state"] == state
    stops = [e for e in _audit(audit) if e["event"] == "session stopped: torque off"]
    assert len(stops) == 1, stops
    assert stops[0]["reason"] == STOP_SIGNALS[signum]
    assert stops[0]["torque_off_confirmed"] is True
    return ended


# --- in-process: every state that drives the arm, both signals ------------------------------------


def test_the_states_that_drive_the_arm_are_the_spec_s() -> None:
    assert TORQUE_STATES == [
        "safety_check", "pilot_installation", "safety_experience", "rom_limits",
        "operative_check", "identification", "training", "compensation",
    ]  # fmt: skip


@pytest.mark.parametrize("name", list(SIGNALS))
@pytest.mark.parametrize("state", [*TORQUE_STATES, "FAIL"])
def test_a_signal_in_a_state_that_drives_the_arm_takes_the_torque_off_first(
    tmp_path: Path, models: Models, state: str, name: str
) -> None:
    signum = SIGNALS[name]
    audit = tmp_path / "audit.jsonl"
    configure_logging("critical", audit)
    session = Session(tmp_path / "session")
    runtime = session.runtime
    timer = threading.Timer(0.05, os.kill, (os.getpid(), signum))
    try:
        if state in ("identification", "training", "compensation", "FAIL"):
            session.select(models.good, models.validation)
        if state == "FAIL":  # a fault whose reaction holds the arm (hold, lower to the rest)
            session.walk_to("compensation")
            session.relax_completely()
            session.hal.inject_fault("bus")
            runtime.runner.pass_time(0.3)
            assert runtime.arm_held
        else:
            session.walk_to(state)
            runtime.runner.pass_time(0.3)
        assert runtime.state_name == state
        assert DriveState.ENABLED in runtime.last_sample.drives  # the arm is driven when the signal comes
        assert np.any(session.hal.applied_motor_torque_nm != 0.0)

        def body() -> tuple[int, str]:
            timer.start()
            runtime.runner.pass_time(600.0)  # lock-step ticks in the main thread: the signal lands in one of them
            return 0, "not signalled"

        said = io.StringIO()
        code = run_session(runtime, Console(file=said, width=200, color_system=None), body)
    finally:
        timer.cancel()
        timer.join()
        if runtime.ended is None:  # the test failed before the session ended
            runtime.shutdown("test failed")
            runtime.close()
    assert code == 128 + signum  # 143, 129
    assert np.all(session.hal.applied_motor_torque_nm == 0.0)
    assert f"state {state}; {STOP_SIGNALS[signum]})" in said.getvalue()  # the line, with the reason
    flush_logs()
    ended = _check_ended(tmp_path / "session", audit, signum, state)
    assert ended["t_s"] < 300.0  # ended by the signal, not by the wait


# --- real processes, one per mode -------------------------------------------------------------------


def _spawn_prompt(tmp_path: Path, out: Path, audit: Path) -> pexpect.spawn:
    env = {**os.environ, "XDG_STATE_HOME": str(tmp_path / "state"), "PROMPT_TOOLKIT_NO_CPR": "1", "TERM": "xterm"}
    child = pexpect.spawn(
        str(DAROR), ["--log-json", str(audit), "console", "--out", str(out)],
        env=env, encoding="utf-8", timeout=60, dimensions=(50, 160),
    )  # fmt: skip
    child.expect(r"\[(\w+)\] >")
    assert child.match.group(1) == "startup", child.before[-3000:]
    child.send("advance\r")
    child.expect(r"advance: (accepted|refused)")  # then the prompt in the state it left the robot in
    child.expect(r"\[(safety_check|FAIL)\] >")
    state = child.match.group(1)
    # real time on a shared machine: a loop stalled by the scheduler faults (watchdog, H5), and a
    # session in FAIL is not the state this test is about
    assert state == "safety_check", f"the loop faulted before the signal (a loaded machine?): {child.before[-2000:]}"
    time.sleep(0.3)
    return child


@pytest.mark.subprocess
@pytest.mark.realtime
@pytest.mark.slow
def test_at_the_prompt_sigterm_and_a_closed_terminal_end_the_session_with_torque_off(tmp_path: Path) -> None:
    out, audit = tmp_path / "term", tmp_path / "term.jsonl"
    child = _spawn_prompt(tmp_path, out, audit)
    child.kill(signal.SIGTERM)
    child.expect(r"torque off at t = [0-9.]+ s: every drive disabled \(state safety_check; terminated \(SIGTERM\)\)")
    child.expect(pexpect.EOF)
    child.close()
    assert child.exitstatus == 143
    _check_ended(out, audit, signal.SIGTERM, "safety_check")
    # the terminal goes away (a closed window, a dropped ssh): the kernel sends SIGHUP; nothing can
    # be printed any more, and the session still ends with torque off and session.json
    out, audit = tmp_path / "hup", tmp_path / "hup.jsonl"
    child = _spawn_prompt(tmp_path, out, audit)
    child.ptyproc.fileobj.close()
    child.closed = True
    _, status = os.waitpid(child.pid, 0)
    child.terminated = True
    assert os.waitstatus_to_exitcode(status) == 129
    _check_ended(out, audit, signal.SIGHUP, "safety_check")


def _until_echoed(process: subprocess.Popen[str], line: str, timeout_s: float = 120.0) -> str:
    """Read the process's output until ``line`` is echoed; what was read."""
    assert process.stdout is not None
    seen: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        text = process.stdout.readline()
        if not text:
            break
        seen.append(text)
        if text.rstrip().endswith(f"> {line}"):
            return "".join(seen)
    raise AssertionError(f"{line!r} was not echoed:\n{''.join(seen)[-3000:]}")


def _signal_at(command: list[str], line: str, signum: int, stdin: str | None = None) -> tuple[int, str]:
    """Run ``command``; once it echoes ``line``, send ``signum``; its exit code and output."""
    process = subprocess.Popen(
        command, stdin=subprocess.PIPE if stdin is not None else subprocess.DEVNULL,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        if stdin is not None:
            assert process.stdin is not None
            process.stdin.write(stdin)  # and left open: the operator has not finished
            process.stdin.flush()
        before = _until_echoed(process, line)
        time.sleep(0.2)
        process.send_signal(signum)
        after, _ = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    return process.returncode, before + after


@pytest.mark.subprocess
def test_a_script_ends_on_sighup_in_operative_check(tmp_path: Path) -> None:
    isb = tmp_path / "isb.yaml"
    isb.write_text(ISB_LIMITS, encoding="utf-8")
    script = tmp_path / "to_operative_check.txt"
    script.write_text(
        "wait 0.5\nadvance\nsim estop operator on\nwait 0.3\nsim estop operator off\nwait 0.5\n"
        "sim estop pilot on\nwait 0.3\nsim estop pilot off\nwait 0.5\nadvance\nconfirm settings\nadvance\n"
        "wait 0.5\nconfirm installation\nadvance\nsim estop pilot on\nwait 0.3\nsim estop pilot off\nwait 0.5\n"
        f"confirm safety_experience\nadvance\nrom load {isb}\nconfirm a_priori_model\nadvance\n"
        "expect state operative_check\nwait 600\n",
        encoding="utf-8",
    )
    out, audit = tmp_path / "session", tmp_path / "audit.jsonl"
    code, printed = _signal_at(
        [str(DAROR), "--log-json", str(audit), "console", "--script", str(script), "--out", str(out)],
        "wait 600",
        signal.SIGHUP,
    )
    assert code == 129, printed[-3000:]
    assert "every drive disabled (state operative_check; hang-up (SIGHUP))" in printed
    assert "Traceback" not in printed
    _check_ended(out, audit, signal.SIGHUP, "operative_check")


@pytest.mark.subprocess
def test_piped_lines_end_on_sigterm_in_pilot_installation(tmp_path: Path) -> None:
    lines = (
        "wait 0.5\nadvance\nsim estop operator on\nwait 0.3\nsim estop operator off\nwait 0.5\n"
        "sim estop pilot on\nwait 0.3\nsim estop pilot off\nwait 0.5\nadvance\nconfirm settings\nadvance\n"
        "wait 1\n"
    )
    out, audit = tmp_path / "session", tmp_path / "audit.jsonl"
    code, printed = _signal_at(
        [str(DAROR), "--log-json", str(audit), "console", "--out", str(out)], "wait 1", signal.SIGTERM, stdin=lines
    )
    assert code == 143, printed[-3000:]
    assert "every drive disabled (state pilot_installation; terminated (SIGTERM))" in printed
    _check_ended(out, audit, signal.SIGTERM, "pilot_installation")


@pytest.mark.subprocess
@pytest.mark.slow
def test_daror_hil_ends_on_sigterm_with_the_torque_off_on_the_bus(tmp_path: Path) -> None:
    script = tmp_path / "hil.txt"
    script.write_text("wait 0.5\nadvance\nexpect state safety_check\nwait 600\n", encoding="utf-8")
    out, audit = tmp_path / "hil", tmp_path / "audit.jsonl"
    code, printed = _signal_at(
        [str(DAROR), "--log-json", str(audit), "hil", "--script", str(script), "--out", str(out)],
        "wait 600",
        signal.SIGTERM,
    )
    assert code == 143, printed[-3000:]
    assert "every drive disabled (state safety_check; terminated (SIGTERM))" in printed
    _check_ended(out, audit, signal.SIGTERM, "safety_check")
    assert json.loads((out / "hil.json").read_text(encoding="utf-8"))["exit_code"] == 143
