"""Issue 24, defect 6: the README's HIL example with a fault writes every file and says how the robot reacted.

``daror hil --script session.txt --fault emcy:2@30`` used to exit 1 with no ``hil.json``, print a
transition stamped ``[t=-]`` after a line stamped 151.8 s, and wait 120 s of robot time in FAIL for
a pilot's sweep that had ended with the fault. Checked here on what an engineer would read: the
files, ``hil.json``'s figures against the audit log and the bus log (the drive's own statusword),
the printed stamps, the robot time the run took.
"""

from __future__ import annotations

import gzip
import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from daror_runtime.cli import main

SESSION = Path(__file__).parents[2] / "daror_runtime" / "console" / "scripts" / "session.txt"
DAROR = Path(sys.executable).with_name("daror")
PERIOD_S = 1.0 / 400.0  # can-sim's default rate (D160)
STAMP = re.compile(r"^\[t=([^\]]*)\]")


@dataclass
class Run:
    out: Path
    code: int
    stdout: str
    stderr: str
    report: dict
    session: dict
    audit: list[dict]


@pytest.fixture(scope="module")
def readme_example(tmp_path_factory: pytest.TempPathFactory) -> Run:
    """The README's example, as a user types it (the ``daror`` command in a process of its own)."""
    out = tmp_path_factory.mktemp("hil") / "hil1"
    done = subprocess.run(
        [str(DAROR), "hil", "--script", str(SESSION), "--out", str(out), "--fault", "emcy:2@30"],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
        env={**os.environ, "COLUMNS": "200"},
    )
    audit = [json.loads(line) for line in (out / "audit.jsonl").read_text().splitlines() if line.strip()]
    return Run(
        out,
        done.returncode,
        done.stdout,
        done.stderr,
        json.loads((out / "hil.json").read_text()),
        json.loads((out / "session.json").read_text()),
        audit,
    )


@pytest.mark.slow
def test_the_run_fails_in_one_line_and_writes_all_its_files(readme_example: Run) -> None:
    run = readme_example
    assert run.code == 1
    assert run.stderr.count("\n") == 1
    assert run.stderr.startswith(f"daror hil: failed: {SESSION}: line 47: 'wait until still' ended early")
    assert sorted(p.name for p in run.out.iterdir()) == ["audit.jsonl", "can.log.gz", "hil.json", "session.json"]
    assert run.report["exit_code"] == 1
    assert "'wait until still' ended early: the robot entered FAIL" in run.report["error"]
    assert run.session["state"] == "FAIL"


@pytest.mark.slow
def test_the_wait_ends_when_the_robot_fails_and_the_reaction_plays_out(readme_example: Run) -> None:
    """The pilot's sweep ran to t = 151.7 s; the wait for it ends in the tick of the fault (30 s), the script
    stops there (line 48 never runs), and robot time runs on only while the reaction lowers the arm."""
    run = readme_example
    assert "[t=29.998 s] wait ended early: the robot is in FAIL" in run.stdout
    assert "session.txt:48 >" not in run.stdout
    phases = [e for e in run.audit if e.get("event") == "reaction phase"]
    assert [e["phase"] for e in phases] == ["lower", "handoff", "held"]
    stopped = next(e for e in run.audit if e.get("event") == "session stopped: torque off")
    assert phases[-1]["t_s"] < stopped["t_s"] < phases[-1]["t_s"] + 0.2  # the session ended once the arm was held
    assert stopped["t_s"] < 50.0  # not the sweep's 151.8 s


@pytest.mark.slow
def test_the_printed_lines_are_in_robot_time_order(readme_example: Run) -> None:
    stamps = [m.group(1) for line in readme_example.stdout.splitlines() if (m := STAMP.match(line))]
    assert "-" not in stamps  # every line has its robot time (the FAIL's transition was [t=-])
    times = [float(s.removesuffix(" s")) for s in stamps]
    assert len(times) > 30
    assert times == sorted(times)
    assert times[-1] > 44.0  # the reaction's last news, the arm held at the rest pose


@pytest.mark.slow
def test_hil_json_says_which_fault_when_and_how_the_robot_reacted(readme_example: Run) -> None:
    (fault,) = readme_example.report["faults"]
    assert (fault["kind"], fault["node"], fault["joint"]) == ("emcy", 2, 2)
    assert fault["scheduled_at_s"] == 30.0
    assert fault["injected_s"] == 30.0
    assert (fault["state_before"], fault["state_after"]) == ("rom_limits", "FAIL")
    assert fault["ticks_to_state_after"] == 0  # in the tick that read the EMCY
    assert [(f["kind"], f["joint"]) for f in fault["found"]] == [("hal", None), ("drive", 2)]
    assert fault["declared_reaction"] == {
        "hal": {"reaction": "lower", "faulted_joint": "with_the_arm"},
        "drive": {"reaction": "lower", "faulted_joint": "off"},
    }
    reaction = fault["reaction"]
    assert (reaction["reaction"], reaction["category"], reaction["joints_off"]) == ("lower", 1, [2])
    assert [p["phase"] for p in reaction["phases"]] == ["lower", "handoff", "held"]
    stages = fault["power_stage"]
    assert all(stages[j]["on_at_injection"] for j in "1234")
    # joint 2's drive ramps its torque out by itself (its fault reaction), within the run
    assert stages["2"]["by_session_end"] is False
    assert 0 < stages["2"]["ticks_to_off"] < 1500  # the spec's ramp is at most 3 s
    # the others held and lowered the arm; their torque went off only when the session ended
    for j in "134":
        assert stages[j]["by_session_end"] is True
        assert stages[j]["ticks_to_off"] == stages["1"]["ticks_to_off"] > stages["2"]["ticks_to_off"]
    line = next(line for line in readme_example.stdout.splitlines() if line.startswith("fault emcy on node 2"))
    assert f"2 after {stages['2']['ticks_to_off']} ticks;" in line


@pytest.mark.slow
def test_the_power_stage_figure_is_the_drives_own_statusword_on_the_bus(readme_example: Run) -> None:
    """Joint 2's drive says FAULT (its ramp ended, power stage off) in the first TPDO after the report's time."""
    run = readme_example
    epoch = run.report["bus"]["traffic_log_epoch_s"]
    off_s = run.report["faults"][0]["power_stage"]["2"]["off_s"]
    states = []
    with gzip.open(run.out / "can.log.gz", "rt") as log:
        for line in log:
            if " 182#" in line:  # node 2's TPDO1: statusword (little endian), motor position
                t_s = float(line[1 : line.index(")")]) - epoch
                if 29.9 <= t_s <= off_s + 0.1:
                    word = int.from_bytes(bytes.fromhex(line.split("#")[1].split()[0][:4]), "little")
                    states.append((t_s, word))
    # CiA 402's statusword masks: OPERATION ENABLED x01x 0111, FAULT REACTION ACTIVE x0xx 1111, FAULT x0xx 1000
    assert states[0][1] & 0x6F == 0x27  # before the fault
    first_fault = next(t for t, word in states if word & 0x4F == 0x08)  # the power stage is off
    assert first_fault == pytest.approx(off_s, abs=2 * PERIOD_S)
    ramping = [word & 0x4F for t, word in states if 30.0 + PERIOD_S < t < first_fault - 2 * PERIOD_S]
    assert ramping
    assert set(ramping) == {0x0F}


@pytest.mark.subprocess
@pytest.mark.slow
def test_the_compressed_bus_log_holds_every_frame_and_can_utils_read_it(readme_example: Run, tmp_path: Path) -> None:
    run = readme_example
    bus = run.report["bus"]
    with gzip.open(run.out / "can.log.gz", "rt") as log:
        lines = sum(1 for _ in log)
    assert lines == bus["frames_sent"] + bus["frames_received"]
    raw_bytes = lines * 38  # a candump -L line of the log is 35 to 46 bytes
    assert (run.out / "can.log.gz").stat().st_size < raw_bytes / 5
    log2asc = shutil.which("log2asc")
    if log2asc is None:
        pytest.skip("can-utils is not installed (the Makefile installs it with apt-get for make test)")
    with subprocess.Popen(["zcat", str(run.out / "can.log.gz")], stdout=subprocess.PIPE) as zcat:
        done = subprocess.run(
            [log2asc, "-O", str(tmp_path / "can.asc"), "daror"], stdin=zcat.stdout, capture_output=True, timeout=120
        )
    assert done.returncode == 0
    with open(tmp_path / "can.asc") as asc:
        body = sum(1 for line in asc if line[:1] == " " or line[:1].isdigit())
    assert body >= lines


def test_a_wait_begun_outside_fail_ends_there_and_one_begun_in_fail_runs_its_course(tmp_path: Path) -> None:
    script = tmp_path / "waits.txt"
    script.write_text("wait 100\nexpect state FAIL\nwait 2\n")
    out = tmp_path / "run"
    assert main(["hil", "--script", str(script), "--out", str(out), "--fault", "drive_fault:1@1"]) == 0
    session = json.loads((out / "session.json").read_text())
    # 1 s to the fault, the 2 s wait in FAIL, the torque off: not the 100 s asked for
    assert session["t_s"] == pytest.approx(3.004, abs=3 * PERIOD_S)
    (fault,) = json.loads((out / "hil.json").read_text())["faults"]
    assert (fault["state_before"], fault["state_after"]) == ("startup", "FAIL")
    assert fault["reaction"]["reaction"] == "off"  # no drive held anything in startup: nothing to lower
    assert not any(stage["on_at_injection"] for stage in fault["power_stage"].values())


def test_the_summary_attributes_only_what_followed_a_fault() -> None:
    """A fault the robot shrugs off is not blamed for a transition or a fault long after it; a scheduled
    fault the session never reached is listed as never injected."""
    from daror_runtime.fsm.spec import load_fsm_spec
    from daror_runtime.hil import ScheduledFault, fault_summaries

    spec = load_fsm_spec(None)
    scheduled = [ScheduledFault("drop_frames", 3, 3, 5.0), ScheduledFault("emcy", 2, 2, 500.0)]
    drive_events = [
        (0.2, 3, "power stage on"),
        (5.0, 3, "injected drop_frames"),
        (9.0, 3, "power stage off"),
    ]
    audit = [
        {"event": "transition", "t_s": 0.1, "source": "startup", "dest": "safety_check"},
        {"event": "fault", "kind": "estop", "t_s": 8.0, "joint": None, "message": "e-stop pressed (operator)"},
        {"event": "transition", "t_s": 9.0, "source": "safety_check", "dest": "settings"},
        {"event": "session stopped: torque off", "t_s": 20.0},
    ]
    dropped, never = fault_summaries(scheduled, drive_events, audit, spec, [1, 2, 3, 4], 500.0)
    assert (dropped["scheduled_at_s"], dropped["injected_s"], dropped["state_before"]) == (5.0, 5.0, "safety_check")
    assert dropped["state_after"] == "safety_check"  # nothing happened within 1 s of it
    assert dropped["ticks_to_state_after"] is None
    assert dropped["found"] == []
    assert dropped["reaction"] is None
    assert dropped["power_stage"]["3"] == {
        "on_at_injection": True, "off_s": 9.0, "ticks_to_off": 2000, "by_session_end": False,
    }  # fmt: skip
    assert dropped["power_stage"]["1"]["on_at_injection"] is False
    assert never == {"kind": "emcy", "node": 2, "joint": 2, "scheduled_at_s": 500.0, "injected_s": None}
