"""The operator console: ``daror console --script``, :class:`ConsoleSession` lines, and typed sessions.

Scripts run lock-step on the simulated plant (``exo_dummy_arm``), so every test here is a few
hundred milliseconds of robot time. Exit codes (daror_runtime/cli.py): 0 done, 1 a check of the
script failed, 2 bad input (an unknown command, a bad spec or settings file), with one stderr line
naming the file and the line or field.
"""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from rich.console import Console

from daror_runtime.cli import main
from daror_runtime.console.commands import CommandError, ConsoleSession, ScriptCheckError
from daror_runtime.console.run import read_script, run_interactive, run_script
from daror_runtime.console.world import SimWorld
from daror_runtime.fsm.spec import DEFAULT_SPEC_PATH
from daror_runtime.logs import configure_logging
from daror_runtime.runtime import RequestRefusedError, Runtime
from hal.sim.backend import SimHal

#: startup -> safety_check (both e-stops tested) -> settings, with checks on the way.
SHORT_SESSION = """\
# startup: drives off until the hardware answers
wait 0.2
advance
expect accepted
expect state safety_check

# safety_check: advance waits for both e-stop tests
advance
expect refused
sim estop operator on
wait 0.1
sim estop operator off
wait 0.2
sim estop pilot on   # the pilot's button
wait 0.1
sim estop pilot off
wait 0.2
advance
expect accepted
expect state settings
"""


@pytest.fixture(autouse=True)
def default_logging() -> Iterator[None]:
    """``main`` configures logging for the process; put the defaults back afterwards."""
    yield
    configure_logging()


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def console(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["console", *map(str, argv)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def one_line(err: str) -> str:
    """The command's own line on stderr (exactly one, the last; the audit log's warnings may precede it)."""
    lines = err.rstrip("\n").split("\n")
    own = [line for line in lines if line.startswith("daror console: ")]
    assert own == lines[-1:], f"not one line of the command, at the end: {err!r}"
    return own[0]


def line_of(script: Path, text: str) -> int:
    """The line number of the first line of ``script`` that is ``text``."""
    return next(n for n, line in read_script(script) if line == text)


# --- daror console --script ----------------------------------------------------------------


def test_a_script_runs_to_its_end_and_writes_the_session(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    script = write(tmp_path / "short.txt", SHORT_SESSION)
    out = tmp_path / "session"
    audit = tmp_path / "audit.jsonl"
    capsys.readouterr()
    code = main(["--log-json", str(audit), "console", "--script", str(script), "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "daror console: " not in captured.err  # no error of the command (the audit log may warn)
    lines = len(read_script(script))
    assert lines == 17  # comments and blank lines are not lines of the script
    assert f"script done: {lines} lines, state settings" in captured.out
    assert "  ok: state settings" in captured.out
    assert "refused (unmet: estop_operator_tested" in captured.out
    document = json.loads((out / "session.json").read_text(encoding="utf-8"))
    assert document["state"] == "settings"
    assert document["number"] == 3
    assert document["transitions"] == 2
    assert document["faults"] == []
    assert document["failures"] == []
    assert document["estop_tested"] == []  # evidence of safety_check's visit, forgotten on leaving it
    assert document["t_s"] == pytest.approx(0.8, abs=0.005)  # robot time: the waits, and a tick per request
    events = [json.loads(line) for line in audit.read_text(encoding="utf-8").splitlines()]
    mine = [e for e in events if e.get("session_id") == document["session_id"]]
    assert [(e["source"], e["dest"]) for e in mine if e["event"] == "transition"] == [
        ("startup", "safety_check"),
        ("safety_check", "settings"),
    ]
    assert [e["buttons"] for e in mine if e["event"] == "e-stop test"] == [["operator"], ["pilot"]]


def test_an_unknown_command_stops_the_script_with_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    script = write(tmp_path / "typo.txt", "wait 0.1\nadvance\n\n# a typo next\nadvanse\nadvance\n")
    out = tmp_path / "session"
    code, stdout, err = console(capsys, "--script", script, "--out", out)
    assert code == 2
    line = one_line(err)
    assert line.startswith("daror console: error: ")
    assert f"{script}: line 5: unknown command 'advanse'" in line
    # the lines before it ran, the one after it did not; the runtime was closed and summarised
    document = json.loads((out / "session.json").read_text(encoding="utf-8"))
    assert document["state"] == "safety_check"
    assert document["transitions"] == 1
    assert "script done" not in stdout


def test_bad_arguments_name_the_line_and_the_usage(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    script = write(tmp_path / "args.txt", "wait 0.1\nsupport lots\n")
    code, _, err = console(capsys, "--script", script, "--out", tmp_path / "session")
    assert code == 2
    assert f"{script}: line 2: support LEVEL: 'lots' is not a number" in one_line(err)


def test_a_failing_expect_exits_1_naming_the_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    script = write(
        tmp_path / "expect.txt", "wait 0.1\nadvance\n# the e-stops were not tested\nadvance\nexpect state settings\n"
    )
    out = tmp_path / "session"
    code, _, err = console(capsys, "--script", script, "--out", out)
    assert code == 1
    line = one_line(err)
    assert line.startswith("daror console: failed: ")
    assert f"{script}: line 5: expected state settings, the robot is in safety_check" in line
    assert json.loads((out / "session.json").read_text(encoding="utf-8"))["state"] == "safety_check"


def test_expect_accepted_after_a_refusal_fails(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    script = write(tmp_path / "expect.txt", "wait 0.1\nadvance\nadvance\nexpect accepted\n")
    code, _, err = console(capsys, "--script", script, "--out", tmp_path / "session")
    assert code == 1
    line = one_line(err)
    assert f"{script}: line 4: expected 'advance' to be accepted; it was refused (unmet: estop_operator_tested" in line


def test_a_bad_spec_refuses_to_start(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = yaml.safe_load(DEFAULT_SPEC_PATH.read_text(encoding="utf-8"))
    doc["states"][1]["guards"]["advance"][0] = "estop_operator_tsted"
    spec = write(tmp_path / "spec.yaml", yaml.safe_dump(doc, sort_keys=False))
    script = write(tmp_path / "short.txt", SHORT_SESSION)
    out = tmp_path / "session"
    code, stdout, err = console(capsys, "--script", script, "--out", out, "--spec", spec)
    assert code == 2
    line = one_line(err)
    assert line.startswith("daror console: error: ")
    assert str(spec) in line
    assert "states.1.guards.advance.0" in line
    assert "estop_operator_tsted" in line
    assert not out.exists()
    assert stdout == ""


@pytest.mark.parametrize(
    ("settings", "field"),
    [
        ("support_levle: 0.8\n", "support_levle"),
        ("support_level: 1.5\n", "support_level"),
        ("identification:\n  waypoint_stride: 0\n", "identification.waypoint_stride"),
    ],
)
def test_bad_settings_refuse_to_start_naming_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], settings: str, field: str
) -> None:
    path = write(tmp_path / "settings.yaml", settings)
    script = write(tmp_path / "short.txt", SHORT_SESSION)
    out = tmp_path / "session"
    code, _, err = console(capsys, "--script", script, "--out", out, "--settings", path)
    assert code == 2
    line = one_line(err)
    assert str(path) in line
    assert field in line
    assert not out.exists()


# --- ConsoleSession ------------------------------------------------------------------------


class Lines:
    """A console session over a lock-step runtime on the simulated plant, printing into a buffer."""

    def __init__(self, directory: Path, world: bool = True) -> None:
        self.hal = SimHal("exo_dummy_arm")
        self.runtime = Runtime(self.hal, directory)
        self.runtime.open()
        self.buffer = io.StringIO()
        out = Console(file=self.buffer, width=400, highlight=False, color_system=None)
        self.session = ConsoleSession(self.runtime, out, SimWorld(self.hal) if world else None)

    def run(self, *lines: str) -> str:
        """Execute ``lines``; what they printed."""
        start = len(self.buffer.getvalue())
        for line in lines:
            self.session.execute(line)
        return self.buffer.getvalue()[start:]

    @property
    def last(self) -> Any:
        return self.session.last.response

    def close(self) -> None:
        self.runtime.close()


@pytest.fixture
def lines(tmp_path: Path) -> Iterator[Lines]:
    session = Lines(tmp_path / "session")
    yield session
    session.close()


TO_SETTINGS = (
    "wait 0.2",
    "advance",
    "sim estop operator on",
    "wait 0.05",
    "sim estop operator off",
    "wait 0.05",
    "sim estop pilot on",
    "wait 0.05",
    "sim estop pilot off",
    "wait 0.05",
    "advance",
    "expect state settings",
)


def test_a_refused_request_is_answered_with_its_reason(lines: Lines) -> None:
    lines.run(*TO_SETTINGS)
    printed = lines.run("advance")
    assert lines.last.request == "advance"
    assert not lines.last.accepted
    assert lines.last.unmet == ("settings_confirmed",)
    assert "advance: refused (unmet: settings_confirmed (the operator confirmed the session settings))" in printed
    lines.run("expect refused")
    with pytest.raises(ScriptCheckError, match="expected 'advance' to be accepted; it was refused"):
        lines.run("expect accepted")
    assert lines.runtime.supervisor.state_name == "settings"
    printed = lines.run("confirm settings", "expect accepted", "advance", "expect state pilot_installation")
    assert "advance: accepted, state pilot_installation" in printed


def test_a_checklist_of_another_state_is_refused(lines: Lines) -> None:
    lines.run(*TO_SETTINGS)
    printed = lines.run("confirm installation")
    assert not lines.last.accepted
    assert lines.last.reason == "state settings has no installation checklist"
    assert "confirm installation: refused (state settings has no installation checklist)" in printed
    assert lines.runtime.signals.confirmed == set()
    with pytest.raises(RequestRefusedError, match="unknown checklist 'straps'"):
        lines.run("confirm straps")
    with pytest.raises(CommandError, match="usage: confirm CHECKLIST"):
        lines.run("confirm")


def test_lines_that_are_not_commands(lines: Lines) -> None:
    with pytest.raises(CommandError, match="unknown command 'advanse'; commands: "):
        lines.run("advanse")
    with pytest.raises(CommandError, match="cannot split"):
        lines.run('sim estop "operator on')
    with pytest.raises(CommandError, match="usage: wait SECONDS"):
        lines.run("wait for 2")
    with pytest.raises(CommandError, match="wait until: expected idle, still, model or state NAME"):
        lines.run("wait until dawn")
    with pytest.raises(CommandError, match="expected a duration >= 0"):
        lines.run("wait -1")
    with pytest.raises(CommandError, match="'nan' is not a finite number"):
        lines.run("support nan")
    assert lines.run("   ", "# only a comment") == ""
    assert lines.runtime.supervisor.state_name == "startup"
    assert lines.runtime.supervisor.transitions == 0


def test_wait_until_a_state_that_does_not_come_fails_the_check(lines: Lines) -> None:
    with pytest.raises(ScriptCheckError, match=r"'wait until state settings' did not happen within 0\.05 s"):
        lines.run("wait until state settings timeout 0.05")
    assert lines.runtime.signals.sample.t_s == pytest.approx(0.05, abs=2e-3)  # the time passed, lock-step


def test_the_simulated_world_acts_on_the_plant(lines: Lines) -> None:
    lines.run("wait 0.2", "advance", "sim estop pilot on", "wait 0.05")
    sample = lines.runtime.signals.sample
    assert sample.estop == (False, True)
    assert lines.runtime.monitor.faulted  # an e-stop test: torque off while pressed
    assert lines.hal.applied_motor_torque_nm.tolist() == [0.0] * 4
    lines.run("sim estop pilot off", "wait 0.05", "sim pilot carry 0.25")
    assert not lines.runtime.monitor.faulted
    assert lines.session.world is not None
    assert lines.session.world.pilot.carried == 0.25
    with pytest.raises(CommandError, match="usage: sim estop"):
        lines.run("sim estop operator maybe")


def test_sim_commands_are_refused_without_a_simulated_world(tmp_path: Path) -> None:
    hardware = Lines(tmp_path / "session", world=False)
    try:
        for line in ("sim estop operator on", "sim fault nan 2", "sim clear", "sim pilot carry 0"):
            with pytest.raises(CommandError, match="this session runs on hardware"):
                hardware.run(line)
        assert hardware.hal.read().estop == (False, False)
        hardware.run("wait 0.1", "advance", "expect state safety_check")  # operator commands still work
    finally:
        hardware.close()


# --- typed sessions ------------------------------------------------------------------------


def test_run_interactive_survives_bad_lines_and_stops_at_quit(lines: Lines) -> None:
    typed = io.StringIO(
        "status\n"
        "wait 0.2\n"
        "advanse\n"  # a typo: answered, the session goes on
        "identify training\n"  # refused before it is queued: not in an identification state
        "wait until state FAIL timeout 0.01\n"  # a check that fails: answered
        "advance\n"
        "quit\n"
        "advance\n"  # never read
    )
    run_interactive(lines.session, typed)
    printed = lines.buffer.getvalue()
    assert lines.runtime.supervisor.state_name == "safety_check"
    assert lines.runtime.supervisor.transitions == 1
    assert typed.read() == "advance\n"  # the line after quit was not consumed
    assert "error: unknown command 'advanse'" in printed
    assert "error: identification runs only in a state with the identification mode, not in startup" in printed
    assert "error: 'wait until state FAIL' did not happen within 0.01 s" in printed
    assert "advance: accepted, state safety_check" in printed
    assert '"state": "startup"' in printed  # the status, as JSON
    assert printed.count("[startup] > ") == 6
    assert printed.count("[safety_check] > ") == 1


def test_run_interactive_ends_at_the_end_of_input_and_shows_help(lines: Lines) -> None:
    run_interactive(lines.session, io.StringIO("help\nwait 0.1\nadvance"))
    printed = lines.buffer.getvalue()
    assert "expect state NAME | expect accepted | expect refused" in printed  # the help text
    assert "sim estop operator|pilot on|off" in printed
    assert lines.runtime.supervisor.state_name == "safety_check"


def test_run_script_counts_the_lines_it_ran(tmp_path: Path, lines: Lines) -> None:
    script = write(tmp_path / "short.txt", SHORT_SESSION)
    result = run_script(lines.session, script)
    assert (result.lines_run, result.state) == (17, "settings")
    assert lines.runtime.supervisor.state_name == "settings"
