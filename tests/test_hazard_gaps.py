"""Tests the mutation run asked for: mitigations of docs/safety.md whose removal no test noticed (issue 26, point 6).

Each test here is a row's test in ``tests/hazard_mutations.yaml``: with the mitigation removed in a
copy of the repository it fails (``pytest -m mutation tests/test_hazard_mutations.py``).

* H7: while the loop runs on its own thread, the interpreter is set so that no other thread can hold
  it long: the switch interval at 0.1 ms, the cyclic collector off with what exists frozen, and both
  given back when the loop stops. Only the bench measured it (a stall the watchdog would fault).
* H8: the torque off at the end of a session is confirmed from a fresh sample of the drives, not
  assumed: a drive that stays enabled is reported as such, in the line the operator reads.
* H12: the safety filter writes torque off while an e-stop is pressed by its own rule; in the loop
  the e-stop's latched fault does it first, so no loop test could tell the rule was gone.
"""

from __future__ import annotations

import gc
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from daror_runtime.clocks import PacedClock
from daror_runtime.runner import REALTIME_SWITCH_INTERVAL_S
from daror_runtime.runtime import Runtime
from daror_runtime.testing import session_core
from hal.config import SimHalConfig
from hal.interface import Command, DriveState, open_hal
from tests.daror_runtime.safety.test_safety_monitor import fresh_monitor, sample
from tests.daror_runtime.session.test_session_safety import Session


@pytest.fixture
def interpreter_settings() -> Iterator[None]:
    """The switch interval and the collector's state before the test, given back after it whatever happens."""
    switch_interval, collector_on = sys.getswitchinterval(), gc.isenabled()
    yield
    sys.setswitchinterval(switch_interval)
    gc.unfreeze()
    if collector_on:
        gc.enable()
    else:
        gc.disable()


@pytest.mark.usefixtures("interpreter_settings")
def test_while_the_loop_runs_on_its_thread_no_other_thread_holds_the_interpreter_long(tmp_path: Path) -> None:
    """H7: the switch interval bounds another thread's hold on the GIL; the collector cannot scan in one."""
    switch_interval = 0.005  # Python's default, whatever an earlier test left (the fixture gives it back)
    sys.setswitchinterval(switch_interval)
    gc.enable()
    gc.unfreeze()
    hal = open_hal(SimHalConfig())
    runtime = Runtime(hal, tmp_path / "session", clock=PacedClock(1.0 / hal.rate_hz))
    runtime.open()
    try:
        runtime.runner.start()
        running = (sys.getswitchinterval(), gc.isenabled(), gc.get_freeze_count())
        runtime.runner.pass_time(0.05)
    finally:
        runtime.shutdown("test")
        runtime.close()
    assert running[0] == pytest.approx(REALTIME_SWITCH_INTERVAL_S)
    assert running[1] is False  # no collection in whichever thread allocates
    assert running[2] > 0  # what existed when the loop started is out of every scan
    # given back when the loop stops
    assert sys.getswitchinterval() == pytest.approx(switch_interval)
    assert gc.isenabled()
    assert gc.get_freeze_count() == 0


def test_a_drive_that_stays_enabled_after_the_torque_off_is_reported_not_confirmed(tmp_path: Path) -> None:
    """H8: the drives are read back after the torque off; one that ignored it is named, never reported off."""
    session = Session(tmp_path / "session")
    runtime = session.runtime
    session.walk_to("pilot_installation")  # the drives hold the arm
    runtime.runner.pass_time(0.1)
    assert runtime.last_sample is not None
    assert DriveState.ENABLED in runtime.last_sample.drives
    hal = session.hal
    write = hal.write
    last = session_core(runtime).loop.last_command  # what the drives apply now
    assert last.enable

    def disobeying_write(command: Command) -> None:
        """The drives keep the last enabled command: a torque off does not reach them."""
        write(command if command.enable else last)

    hal.write = disobeying_write  # type: ignore[method-assign]
    ended = runtime.shutdown("quit")
    assert ended.confirmed is False
    assert "enabled" in ended.drives
    assert "NOT confirmed" in ended.sentence()
    assert np.any(hal.applied_motor_torque_nm != 0.0)  # what the operator is told is what the drives do
    hal.write = write  # type: ignore[method-assign]
    runtime.close()


def test_the_filter_writes_torque_off_while_an_estop_is_pressed_latched_or_not() -> None:
    """H12: the safety filter itself keeps the torque off while a button is pressed, not only through the
    e-stop's latched fault (in the loop the fault is latched first, which hides the filter's own rule)."""
    monitor = fresh_monitor()
    pressed = sample(2, estop=(True, False))
    assert not monitor.faulted  # not checked yet: nothing latched
    assert monitor.filter(Command(np.ones(4), True), pressed).enable is False
    assert monitor.filter(Command(np.ones(4), True), sample(3)).enable  # released: the command passes
