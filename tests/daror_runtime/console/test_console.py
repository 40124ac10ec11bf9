"""The operator console: ``daror console --script``, :class:`ConsoleSession` lines, and typed sessions.

Scripts run lock-step on the simulated plant (``exo_dummy_arm``), so every test here is a few
hundred milliseconds of robot time. Exit codes (daror_runtime/cli/): 0 done, 1 a check of the
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
from daror_runtime.console.grammar import COMMANDS, check_lines
from daror_runtime.console.guide import unguided_steps_cover_every_guard
from daror_runtime.console.run import read_script, run_piped, run_script
from daror_runtime.console.world import SimWorld
from daror_runtime.fsm.spec import DEFAULT_SPEC_PATH
from daror_runtime.logs import configure_logging
from daror_runtime.runtime import RequestRefusedError, Runtime
from daror_runtime.testing import session_core
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


def test_a_bad_line_anywhere_stops_the_script_before_it_runs_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    script = write(tmp_path / "typo.txt", "wait 0.1\nadvance\n\n# a typo next\nadvanse\nadvance\n")
    out = tmp_path / "session"
    code, stdout, err = console(capsys, "--script", script, "--out", out)
    assert code == 2
    line = one_line(err)
    assert line.startswith("daror console: error: ")
    assert f"{script}: line 5: unknown command 'advanse'" in line
    # checked whole before the first line ran: no session, no directory, no file
    assert not out.exists()
    assert stdout == ""


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("support lots", "support LEVEL: 'lots' is not a number"),
        ("support 1.5", "support LEVEL: expected a number between 0 and 1, got 1.5"),
        ("train banana", "train KIND: 'banana' is not one of"),
        ("confirm straps", "confirm CHECKLIST: 'straps' is not one of"),
        ("expect state nowhere", "expect state: 'nowhere' is not one of startup"),
        ("wait until state nowhere", "wait until state: 'nowhere' is not one of"),
        ("rom load missing.yaml", "rom load FILE: missing.yaml: file not found"),
        ("model missing.json", "model FILE: missing.json: file not found"),
        ("sim pilot carry 3", "sim pilot carry SHARE: expected a number between 0 and 1, got 3"),
        ("sim fault meteor", "sim fault KIND: 'meteor' is not one of"),
        ("wait -1", "wait SECONDS: expected a number between 0 and 86400, got -1"),
    ],
)
def test_bad_words_are_refused_before_the_script_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, problem: str
) -> None:
    script = write(tmp_path / "args.txt", f"wait 0.1\nadvance\n{text}\n")
    out = tmp_path / "session"
    code, stdout, err = console(capsys, "--script", script, "--out", out)
    assert code == 2
    assert f"{script}: line 3: {problem}" in one_line(err)
    assert not out.exists()
    assert stdout == ""


def test_a_corrupted_model_file_is_refused_before_the_script_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    broken = write(tmp_path / "model.json", '{"format": "daror-model", "format_version": 1, "kind": "plf+"')
    script = write(tmp_path / "model.txt", f"wait 0.1\nmodel {broken}\n")
    out = tmp_path / "session"
    code, _, err = console(capsys, "--script", script, "--out", out)
    assert code == 2
    assert f"{script}: line 2: model: {broken}: not valid JSON" in one_line(err)
    assert not out.exists()


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
        self.session = ConsoleSession(self.runtime, out, SimWorld(self.hal.world) if world else None)

    def run(self, *lines: str) -> str:
        """Execute ``lines``; what they printed."""
        start = len(self.buffer.getvalue())
        for line in lines:
            self.session.execute(line)
        return self.buffer.getvalue()[start:]

    @property
    def last(self) -> Any:
        return self.session.tally.response

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
    assert lines.runtime.state_name == "settings"
    printed = lines.run("confirm settings", "expect accepted", "advance", "expect state pilot_installation")
    assert "advance: accepted, state pilot_installation" in printed


def test_a_checklist_of_another_state_is_refused(lines: Lines) -> None:
    lines.run(*TO_SETTINGS)
    printed = lines.run("confirm installation")
    assert not lines.last.accepted
    assert lines.last.reason == "state settings has no installation checklist"
    assert "confirm installation: refused (state settings has no installation checklist)" in printed
    assert session_core(lines.runtime).signals.confirmed == set()
    with pytest.raises(CommandError, match="'straps' is not one of settings, installation"):
        lines.run("confirm straps")
    with pytest.raises(CommandError, match="usage: confirm CHECKLIST"):
        lines.run("confirm")
    with pytest.raises(RequestRefusedError, match="unknown checklist 'straps'"):
        lines.runtime.confirm("straps")  # the runtime checks too, for callers other than the console


def test_lines_that_are_not_commands(lines: Lines) -> None:
    with pytest.raises(CommandError, match="unknown command 'advanse'; type help for the list of commands"):
        lines.run("advanse")
    with pytest.raises(CommandError, match="cannot split"):
        lines.run('sim estop "operator on')
    with pytest.raises(CommandError, match="usage: wait SECONDS"):
        lines.run("wait for 2")
    with pytest.raises(CommandError, match="wait until: expected idle, still, model or state NAME"):
        lines.run("wait until dawn")
    with pytest.raises(CommandError, match="expected a number between 0 and 86400"):
        lines.run("wait -1")
    with pytest.raises(CommandError, match="'nan' is not a finite number"):
        lines.run("support nan")
    assert lines.run("   ", "# only a comment") == ""
    assert lines.runtime.state_name == "startup"
    assert session_core(lines.runtime).supervisor.transitions == 0


def test_wait_until_a_state_that_does_not_come_fails_the_check(lines: Lines) -> None:
    with pytest.raises(ScriptCheckError, match=r"'wait until state settings' did not happen within 0\.05 s"):
        lines.run("wait until state settings timeout 0.05")
    assert lines.runtime.last_sample.t_s == pytest.approx(0.05, abs=2e-3)  # the time passed, lock-step


def test_the_simulated_world_acts_on_the_plant(lines: Lines) -> None:
    lines.run("wait 0.2", "advance", "sim estop pilot on", "wait 0.05")
    sample = lines.runtime.last_sample
    assert sample.estop == (False, True)
    assert session_core(lines.runtime).monitor.faulted  # an e-stop test: torque off while pressed
    assert lines.hal.applied_motor_torque_nm.tolist() == [0.0] * 4
    lines.run("sim estop pilot off", "wait 0.05", "sim pilot carry 0.25")
    assert not session_core(lines.runtime).monitor.faulted
    assert lines.session.world is not None
    assert lines.session.world.pilot_carried == 0.25
    with pytest.raises(CommandError, match="sim estop: 'maybe' is not one of on, off"):
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


# --- lines piped in ------------------------------------------------------------------------


def test_piped_lines_are_echoed_answered_and_the_session_goes_on(lines: Lines) -> None:
    piped = io.StringIO(
        "status\n"
        "wait 0.2\n"
        "advanse\n"  # a typo: answered, the session goes on
        "identify training\n"  # refused before it is queued: not in an identification state
        "wait until state FAIL timeout 0.01\n"  # a check that fails: answered
        "advance\n"
        "quit\n"
        "advance\n"  # never read
    )
    code = run_piped(lines.session, piped)
    printed = lines.buffer.getvalue()
    assert code == 2  # a line was not a command
    assert lines.runtime.state_name == "safety_check"
    assert session_core(lines.runtime).supervisor.transitions == 1
    assert piped.read() == "advance\n"  # the line after quit was not consumed
    for line in ("status", "wait 0.2", "advanse", "identify training", "advance", "quit"):
        assert f"> {line}\n" in printed  # every command echoed
    assert "error: unknown command 'advanse'" in printed
    assert "failed: identification runs only in a state with the identification mode, not in startup" in printed
    assert "failed: 'wait until state FAIL' did not happen within 0.01 s" in printed
    assert "advance: accepted, state safety_check" in printed
    assert "state 1 startup (pre_op)" in printed  # the status view
    assert lines.session.tally.failed == 2


def test_piped_lines_exit_1_when_a_request_is_refused_and_0_when_all_went_well(tmp_path: Path) -> None:
    refused = Lines(tmp_path / "a")
    try:
        assert run_piped(refused.session, io.StringIO("wait 0.1\nadvance\nadvance\n")) == 1  # e-stops untested
    finally:
        refused.close()
    fine = Lines(tmp_path / "b")
    try:
        assert run_piped(fine.session, io.StringIO("wait 0.1\nadvance\nadvance\nexpect refused\n")) == 0
    finally:
        fine.close()


def test_help_is_plain_words_for_every_command(lines: Lines) -> None:
    printed = lines.run("help")
    for spec in COMMANDS:
        assert spec.usage in printed
        assert spec.summary in printed
        detail = lines.run(f"help {spec.name}")
        assert spec.usage in detail
        for markup in ("``", "::", ":class:", ":meth:", "**"):
            assert markup not in printed + detail
    with pytest.raises(CommandError, match="help: no command 'flying'"):
        lines.run("help flying")


def test_run_script_counts_the_lines_it_ran(tmp_path: Path, lines: Lines) -> None:
    script = write(tmp_path / "short.txt", SHORT_SESSION)
    checked = check_lines(read_script(script), str(script), lines.session.context)
    result = run_script(lines.session, script, checked)
    assert (result.lines_run, result.state) == (17, "settings")
    assert lines.runtime.state_name == "settings"


def test_every_guard_a_spec_may_name_has_a_next_step() -> None:
    assert unguided_steps_cover_every_guard() == []


def test_the_status_says_what_the_a_priori_model_leaves_out(lines: Lines) -> None:
    """docs/safety.md H15: the settings say no Dummy Arm, the simulated plant carries one."""
    printed = lines.run(
        *TO_SETTINGS, "confirm settings", "advance", "confirm installation", "advance",
        "sim estop pilot on", "wait 0.05", "sim estop pilot off", "wait 0.05", "confirm safety_experience", "advance",
        "expect state rom_limits", "status",
    )  # fmt: skip
    assert "note: the simulated plant carries the Dummy Arm but the settings say dummy_arm: false" in printed
    assert "the A Priori model (the design values of the DAROR-01 only, without the pilot's arm)" in printed
    assert "type: confirm a_priori_model" in printed
    assert "compensation_model_approved: the compensation model is approved for this pilot" in printed
