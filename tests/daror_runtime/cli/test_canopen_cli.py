"""``daror hil`` and the CAN configurations at the command line: what a user types, what comes out.

A scheduled fault happens at its robot time and is in ``hil.json``; bad input is one line, exit 2,
nothing written (no ``can.log.gz``, no ``hil.json``); an existing log is never overwritten; a rate
over the bus-load budget is refused with the numbers.
"""

from __future__ import annotations

import gzip
import json
import time
from pathlib import Path

import pytest

from daror_runtime.cli import main

SCRIPT = """\
# startup (drives off; a fault here fails the robot), then safety_check (minimal impedance)
wait 2.5
advance
wait 1
"""


def _script(tmp_path: Path) -> Path:
    path = tmp_path / "short.txt"
    path.write_text(SCRIPT)
    return path


def _one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    assert "Traceback" not in err
    return err


def test_a_scheduled_fault_happens_at_its_robot_time_and_is_reported(tmp_path: Path) -> None:
    out = tmp_path / "run"
    code = main(["hil", "--script", str(_script(tmp_path)), "--out", str(out), "--fault", "drive_fault:3@1.5"])
    assert code == 0  # the script ran to its end (its advance was refused in FAIL, as it should be)
    report = json.loads((out / "hil.json").read_text())
    (fault,) = report["faults"]
    assert (fault["kind"], fault["node"], fault["joint"], fault["scheduled_at_s"]) == ("drive_fault", 3, 3, 1.5)
    assert fault["injected_s"] == 1.5  # a SYNC falls on 1.5 s at 400 Hz
    assert (fault["state_before"], fault["state_after"]) == ("startup", "FAIL")
    assert report["bus"]["rate_hz"] == 400.0
    events = [json.loads(line) for line in (out / "audit.jsonl").read_text().splitlines()]
    fail = next(e for e in events if e.get("event") == "transition" and e["dest"] == "FAIL")
    # the EMCY at the SYNC of 1.5 s; the FAIL in the tick that reads it, stamped with the time of the
    # last sample read before it (the read that raised has none)
    period_s = 1.0 / report["bus"]["rate_hz"]
    assert 1.5 - period_s - 1e-9 <= fail["t_s"] <= 1.5 + 3 * period_s
    assert any("drive 3: EMCY 0x2310" in e.get("message", "") for e in events if e.get("event") == "fault")
    epoch = report["bus"]["traffic_log_epoch_s"]
    with gzip.open(out / "can.log.gz", "rt") as log:
        emcy = [line for line in log.read().splitlines() if " 083#" in line]
    assert emcy, "no EMCY of node 3 on the bus"
    assert float(emcy[0][1 : emcy[0].index(")")]) - epoch == pytest.approx(1.5, abs=0.003)


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--fault", "heartbeat_loss:2"], "expected KIND:NODE@T_S"),
        (["--fault", "overheat:2@1"], "unknown fault 'overheat'"),
        (["--fault", "emcy:9@1"], "node 9 is not a drive"),
        (["--fault", "emcy:2@-1"], "expected KIND:NODE@T_S"),
        (["--rate-hz", "1000"], "the bus's worst cycle would be 168.0 % loaded"),
        (["--rate-hz", "-3"], "rate_hz: Input should be greater than 0"),
        (["--scenario", "no_such_scenario"], "no_such_scenario"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], fragment: str
) -> None:
    out = tmp_path / "run"
    code = main(["hil", "--script", str(_script(tmp_path)), "--out", str(out), *args])
    assert code == 2
    assert fragment in _one_line_error(capsys)
    assert not (out / "can.log.gz").exists()
    assert not (out / "hil.json").exists()


@pytest.mark.parametrize("name", ["can.log.gz", "can.log"])  # this run's log, and an earlier version's
def test_an_existing_bus_log_is_never_overwritten(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / name).write_text("an earlier run's log\n")
    assert main(["hil", "--script", str(_script(tmp_path)), "--out", str(out)]) == 2
    assert f"{name}: exists" in _one_line_error(capsys)
    assert (out / name).read_text() == "an earlier run's log\n"
    assert sorted(p.name for p in out.iterdir()) == [name]


def test_a_can_sim_configuration_on_a_real_interface_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "hal.yaml"
    config.write_text("backend: can-sim\ninterface: socketcan\nchannel: can0\n")
    assert (
        main(["console", "--hal-config", str(config), "--script", str(_script(tmp_path)), "--out", str(tmp_path / "s")])
        == 2
    )
    assert "the simulated drives live on python-can's 'virtual' bus" in _one_line_error(capsys)


def test_a_can_backend_refuses_lock_step_and_says_which_interface_is_missing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Hardware never runs in lock-step (exit 2); in real time a missing adapter is one line (exit 1)."""
    config = tmp_path / "hal.yaml"
    config.write_text("backend: can\ninterface: socketcan\nchannel: can9\n")
    script = str(_script(tmp_path))
    assert main(["console", "--hal-config", str(config), "--script", script, "--out", str(tmp_path / "s1")]) == 2
    assert "lock-step" in _one_line_error(capsys)
    code = main(
        ["console", "--hal-config", str(config), "--script", script, "--realtime", "--out", str(tmp_path / "s2")]
    )
    assert code == 1
    err = _one_line_error(capsys)
    assert "CAN interface 'socketcan' channel 'can9': cannot be opened" in err


def _robot_time_log(out: Path) -> list[str]:
    epoch = json.loads((out / "hil.json").read_text())["bus"]["traffic_log_epoch_s"]
    lines = []
    with gzip.open(out / "can.log.gz", "rt") as log:
        text = log.read()
    for line in text.splitlines():
        stamp, rest = line[1:].split(")", 1)
        lines.append(f"{float(stamp) - epoch:.6f}{rest}")
    return lines


def test_lock_step_over_can_sim_is_deterministic(tmp_path: Path) -> None:
    """Two runs of one script: the same frames, in the same order, at the same robot times, byte for byte."""
    script = str(_script(tmp_path))
    runs = [tmp_path / "one", tmp_path / "two"]
    for out in runs:
        assert main(["hil", "--script", script, "--out", str(out), "--fault", "drop_frames:2@2.0"]) == 0
    first, second = (_robot_time_log(out) for out in runs)
    assert len(first) > 10_000
    assert first == second


def _real_time_session(tmp_path: Path, out: Path) -> tuple[float, dict[str, object], list[dict[str, object]]]:
    """One ``daror console --hal can-sim --realtime`` of the short script: its wall time, session.json, its faults."""
    started = time.monotonic()
    code = main(["console", "--hal", "can-sim", "--realtime", "--script", str(_script(tmp_path)), "--out", str(out)])
    wall_s = time.monotonic() - started
    assert code == 0
    events = [json.loads(line) for line in (out / "audit.jsonl").read_text().splitlines()]
    faults: list[dict[str, object]] = []
    for event in (e for e in events if e.get("event") == "fault"):  # the monitor's, and the supervisor's lists
        faults += [event] if "kind" in event else list(event.get("faults") or [{"kind": "unknown", **event}])
    return wall_s, json.loads((out / "session.json").read_text()), faults


@pytest.mark.realtime
@pytest.mark.slow
def test_an_operator_session_runs_over_can_sim_in_real_time(tmp_path: Path) -> None:
    """``daror console --hal can-sim --realtime``: the loop on the wall clock over the simulated bus.

    It needs real time: the loop's overrun watchdog faults a stall of more than three periods (7.5 ms
    at 400 Hz), which a loaded CI machine may cause (issue 26: one 6 ms stall failed it). An overrun
    fault is this machine's, not the runtime's, when its own measure (the message) shows the stall:
    then the session runs once more, and a second stall skips the test with both measures. Any other
    fault, or an overrun without a measured stall, fails it.
    """
    stalls: list[str] = []
    for attempt in range(2):
        wall_s, session, faults = _real_time_session(tmp_path, tmp_path / f"session{attempt}")
        assert wall_s >= 3.5  # 3.5 s of robot time took as long (real time, not lock-step)
        others = [f for f in faults if f["kind"] != "overrun"]
        assert not others, f"a fault in a quiet real-time session: {others}"
        overruns = [str(f.get("message", "")) for f in faults]
        if not overruns:
            assert session["state"] == "safety_check"  # startup's advance, after 2.5 s of drives off
            return
        assert all("missed" in message or "stalled" in message for message in overruns), overruns
        stalls.append("; ".join(overruns))
    pytest.skip(f"this machine stalled the real-time loop in both runs: {' | '.join(stalls)}")
