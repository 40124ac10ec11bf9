"""``daror rt-check``: the verdict from figures (injected), a short real run's report (consistent numbers), bad input.

The real runs are short (1 s) and run in a child process, so that ``SCHED_FIFO`` and ``mlockall``
never touch the test process. Their figures depend on the machine's load; the assertions are on
the report's structure and the consistency of its numbers, never on speed.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from daror_runtime.cli import main
from daror_runtime.logs import configure_logging
from daror_runtime.rt_check import Lateness, RtFigures, judge, measured_backend, run_rt_check
from hal.config import hal_config


@pytest.fixture(autouse=True)
def default_logging() -> Iterator[None]:
    """``main`` configures logging for the process; put the defaults back afterwards."""
    yield
    configure_logging()


def _figures(**changes: Any) -> RtFigures:
    figures = RtFigures(
        rate_hz=1000.0,
        duration_s=30.0,
        ticks=29_998,
        lateness=Lateness(p50_us=0.2, p99_us=0.4, p99_9_us=12.0, max_us=420.0),
        overruns=2,
        missed_deadlines=2,
        watchdog_faults=0,
        first_fault_s=None,
        scheduling="SCHED_FIFO 50, memory locked",
        load_average=(0.61, 0.68, 0.83),
        cpus=2,
    )
    return dataclasses.replace(figures, **changes)


# --- the verdict ---------------------------------------------------------------------------------


def test_a_quiet_pc_can_run_the_robot_and_the_line_has_the_figures() -> None:
    verdict = judge(_figures())
    assert verdict.can_run
    assert verdict.line == (
        "this PC can run the robot at 1000 Hz: no overrun fault in 30.0 s, worst tick 0.42 ms late (a stall of 3 ms "
        "faults), p99.9 12.0 us, 2 missed deadlines in 29998 ticks; SCHED_FIFO 50, memory locked; "
        "load 0.61 0.68 0.83 on 2 CPUs"
    )


def test_one_overrun_fault_is_a_no_with_when_a_session_would_have_failed() -> None:
    verdict = judge(
        _figures(
            duration_s=45.0,
            watchdog_faults=18,
            first_fault_s=3.3,
            lateness=Lateness(0.3, 50.0, 3100.0, 19_600.0),
            scheduling="ordinary scheduling (SCHED_FIFO refused)",
            load_average=(3.1, 2.0, 1.2),
        )
    )
    assert not verdict.can_run
    assert verdict.line == (
        "this PC cannot run the robot at 1000 Hz: the overrun watchdog faulted 18 times in 45.0 s, the first after "
        "3.3 s (a session fails then); worst tick 19.60 ms late (a stall of 3 ms faults), p99.9 3100.0 us, "
        "2 missed deadlines in 29998 ticks; ordinary scheduling (SCHED_FIFO refused); load 3.10 2.00 1.20 on 2 CPUs; "
        "check again where SCHED_FIFO is granted"
    )
    assert "faulted once in" in judge(_figures(watchdog_faults=1, first_fault_s=1.6)).line


def test_no_fault_but_less_than_a_margin_of_two_is_a_no() -> None:
    """The watchdog faults a stall of 3 periods; the worst tick may use at most half of it (D141)."""
    assert judge(_figures(lateness=Lateness(0.2, 0.4, 12.0, 1500.0))).can_run  # exactly half: yes
    tight = judge(_figures(lateness=Lateness(0.2, 0.4, 12.0, 1501.0)))
    assert not tight.can_run
    assert tight.line.startswith(
        "this PC cannot run the robot at 1000 Hz with a margin: no overrun fault in 30.0 s, but the worst tick was "
        "1.50 ms late, more than half the 3 ms stall the watchdog faults; "
    )
    assert not tight.line.endswith("check again where SCHED_FIFO is granted")  # it was granted


def test_the_limit_follows_the_rate() -> None:
    """At 500 Hz (a CAN bus's rate) the watchdog faults a stall of 6 ms: 2 ms late is within the margin."""
    slow = judge(_figures(rate_hz=500.0, lateness=Lateness(0.2, 0.4, 12.0, 2000.0)))
    assert slow.can_run
    assert "at 500 Hz" in slow.line
    assert "(a stall of 6 ms faults)" in slow.line
    assert _figures(rate_hz=500.0).stall_limit_ms == 6.0


# --- a short real run ----------------------------------------------------------------------------


def _check_report(report: dict[str, Any], seconds: float, rate_hz: float) -> None:
    """The report's numbers agree with each other and with what was asked."""
    f = report["figures"]
    period = 1.0 / rate_hz
    assert f["rate_hz"] == rate_hz
    assert report["seconds"] == seconds
    # every deadline of the grid was either ticked or skipped; the run covered the time asked
    skipped = f["missed_deadlines"] - f["overruns"]
    assert report["deadlines"] == f["ticks"] + skipped
    assert report["deadlines"] >= round(seconds * rate_hz)
    assert f["ticks"] > 0.5 * seconds * rate_hz
    assert f["duration_s"] >= (report["deadlines"] - 2) * period  # a tick never starts before its deadline
    late = f["lateness"]
    assert 0.0 <= late["p50_us"] <= late["p99_us"] <= late["p99_9_us"] <= late["max_us"]
    assert f["overruns"] <= f["missed_deadlines"]
    if f["watchdog_faults"]:
        assert 0.0 <= f["first_fault_s"] <= f["duration_s"]
        assert len(report["watchdog_messages"]) == min(5, f["watchdog_faults"])
        assert late["max_us"] > 0.0
    else:
        assert f["first_fault_s"] is None
        assert report["watchdog_messages"] == []
    assert report["other_faults"] == []  # the plant holds still: only the watchdog may fault
    assert 0.0 < report["tick_work_mean_us"] <= report["tick_work_max_us"]
    assert len(f["load_average"]) == len(report["load_average_start"]) == 3
    # the verdict is the one the figures give
    figures = RtFigures(**{**f, "lateness": Lateness(**late), "load_average": tuple(f["load_average"])})
    assert report["verdict"] == dataclasses.asdict(judge(figures))


def test_a_one_second_run_in_process_reports_consistent_figures() -> None:
    backend, plant = measured_backend(hal_config("sim"))
    report = run_rt_check(backend, plant, 1.0, realtime=False)
    document = json.loads(json.dumps(report.as_dict()))
    _check_report(document, 1.0, 1000.0)
    assert document["fifo_priority"] is None
    assert document["figures"]["scheduling"] == "ordinary scheduling (SCHED_FIFO not asked for)"
    assert document["machine"]["date_utc"]


@pytest.mark.subprocess
def test_daror_rt_check_writes_its_report_and_exits_with_its_verdict(tmp_path: Path) -> None:
    """The command in a child process (SCHED_FIFO and mlockall when granted), at the can backend's 400 Hz (D160)."""
    out = tmp_path / "rt.json"
    config = tmp_path / "robot.yaml"
    config.write_text("backend: can\ninterface: socketcan\nchannel: can9\n")  # only its rate is used
    daror = Path(sys.executable).with_name("daror")
    run = subprocess.run(
        [str(daror), "rt-check", "--seconds", "1", "--hal-config", str(config), "--json", str(out)],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert run.returncode in (0, 1), run.stderr
    report = json.loads(out.read_text())
    assert report["backend"] == "can"
    _check_report(report, 1.0, 400.0)
    assert report["verdict"]["can_run"] == (run.returncode == 0)
    lines = run.stdout.splitlines()
    assert lines[0] == "rt-check: the real loop at 400 Hz (the can backend's rate) on the simulated plant for 1 s ..."
    assert report["verdict"]["line"] in lines
    assert lines[-1] == f"{out}: written"
    assert run.stderr == ""  # the watchdog's faults are in the report, not logged on the terminal


# --- bad input -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seconds", "0"], "--seconds 0: expected a duration in s, more than 0 and at most 3600"),
        (["--seconds", "nan"], "--seconds nan: expected a duration in s, more than 0 and at most 3600"),
        (["--seconds", "7200"], "--seconds 7200: expected a duration in s, more than 0 and at most 3600"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_nothing_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    out = tmp_path / "rt.json"
    assert main(["rt-check", *argv, "--json", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"daror rt-check: error: {message}"
    assert not out.exists()


def test_a_json_path_that_is_a_folder_or_a_missing_config_is_refused_before_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["rt-check", "--seconds", "1", "--json", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert err.startswith(f"daror rt-check: error: {tmp_path}")
    out = tmp_path / "rt.json"
    assert main(["rt-check", "--hal-config", str(tmp_path / "missing.yaml"), "--json", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert "missing.yaml" in err
    assert not out.exists()
