"""A backend that drives hardware, before one exists: the stand-in drives (tests/standin_drives.py).

The backend owns its time: lock-step (a virtual clock) is refused on a backend that drives
hardware, by the runtime and by ``daror console`` (exit 2, one line, nothing written). The console
asks the backend for its simulated world and, on hardware, has none: ``sim`` lines are refused.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from daror_runtime.cli import main
from daror_runtime.clocks import LockStepClock, LockStepRefusedError, RealTimeClock, check_clock, clock_for
from daror_runtime.console.commands import CommandError
from daror_runtime.console.run import make_session, world_for
from daror_runtime.console.world import SimWorld
from daror_runtime.errors import InputError, UsageError
from daror_runtime.logs import configure_logging
from daror_runtime.runtime import Runtime
from hal.config import hal_config
from hal.errors import HalNotOpenError
from hal.interface import backend_entry, open_hal, register_backend
from hal.registry import registry_restored
from hal.sim.backend import SimHal
from tests.standin_drives import TARGET, StandInDrives

REFUSAL = (
    "the stand-in HAL backend drives hardware: it cannot run lock-step (virtual time); "
    "run it in real time (daror console --realtime)"
)


@pytest.fixture(autouse=True)
def default_logging() -> Iterator[None]:
    """``main`` configures logging for the process; put the defaults back afterwards."""
    yield
    configure_logging()


@pytest.fixture
def drives_as_can() -> Iterator[None]:
    """The stand-in registered as the ``can`` backend (its configuration model kept), restored afterwards."""
    with registry_restored():
        register_backend(replace(backend_entry("can"), target=TARGET))
        yield


class WallClockSimulation(StandInDrives):
    """A backend on wall-clock time that drives no hardware (e.g. simulated drives on a virtual bus in real time)."""

    kind = "wall-clock"
    drives_hardware = False


# --- clocks and backends -----------------------------------------------------------------------------


def test_clocks_say_whether_their_time_is_virtual() -> None:
    assert LockStepClock(1e-3).virtual

    class Late(LockStepClock):
        pass

    assert Late(1e-3).virtual
    assert not RealTimeClock(1e-3).virtual


def test_backends_say_whether_they_own_their_time_and_drive_hardware() -> None:
    sim = SimHal("exo")
    assert (sim.virtual_time, sim.drives_hardware) == (True, False)
    drives = StandInDrives()
    assert (drives.virtual_time, drives.drives_hardware) == (False, True)
    assert drives.world is None
    assert sim.world is not None


def test_the_default_clock_is_the_backends() -> None:
    assert isinstance(clock_for(SimHal("exo")), LockStepClock)
    clock = clock_for(StandInDrives(rate_hz=500.0))
    assert isinstance(clock, RealTimeClock)
    assert clock.period_s == 1 / 500.0


def test_lock_step_is_refused_on_hardware_in_one_line() -> None:
    with pytest.raises(LockStepRefusedError) as caught:
        check_clock(LockStepClock(1e-3), StandInDrives())
    assert str(caught.value) == REFUSAL
    assert isinstance(caught.value, UsageError)
    assert isinstance(caught.value, InputError)  # the command line exits 2
    with pytest.raises(LockStepRefusedError, match="the wall-clock HAL backend runs on wall-clock time"):
        check_clock(LockStepClock(1e-3), WallClockSimulation())
    check_clock(RealTimeClock(1e-3), StandInDrives())  # real time on hardware: fine
    check_clock(RealTimeClock(1e-3), SimHal("exo"))  # the simulated plant at wall-clock rate: fine
    check_clock(LockStepClock(1e-3), SimHal("exo"))


def test_the_runtime_refuses_lock_step_on_hardware_before_anything_is_written(tmp_path: Path) -> None:
    directory = tmp_path / "session"
    with pytest.raises(LockStepRefusedError, match="drives hardware: it cannot run lock-step"):
        Runtime(StandInDrives(), directory, clock=LockStepClock(1e-3))
    assert not directory.exists()


@pytest.mark.slow
def test_the_runtime_runs_a_backend_on_its_own_time_by_default(tmp_path: Path) -> None:
    on_hardware = Runtime(StandInDrives(), tmp_path / "a")
    assert isinstance(on_hardware.runner.clock, RealTimeClock)
    assert not on_hardware.lock_step
    simulated = Runtime(SimHal("exo"), tmp_path / "b")
    assert isinstance(simulated.runner.clock, LockStepClock)
    assert simulated.lock_step
    realtime = Runtime(SimHal("exo"), tmp_path / "c", clock=RealTimeClock(1e-3))
    assert not realtime.lock_step


# --- the console on hardware ---------------------------------------------------------------------------


def test_there_is_no_simulated_world_on_hardware(tmp_path: Path) -> None:
    drives = StandInDrives()
    drives.open()
    assert drives.world is None
    with pytest.raises(UsageError, match="drives hardware and has no simulated world"):
        SimWorld(drives.world)
    runtime = Runtime(StandInDrives(), tmp_path / "session")
    runtime.open()
    try:
        assert world_for(runtime) is None
        session = make_session(runtime)
        assert session.world is None
        assert not session.context.has_world
        assert session.context.fault_kinds == ()
        for line in ("sim estop operator on", "sim fault bus", "sim pilot carry 0"):
            with pytest.raises(CommandError, match="this session runs on hardware"):
                session.execute(line)
        session.execute("expect state startup")  # operator commands are the console's, on any backend
    finally:
        runtime.close()


def test_the_simulated_world_needs_an_open_backend() -> None:
    with pytest.raises(HalNotOpenError):
        SimWorld(SimHal("exo").world)


def test_console_script_on_hardware_exits_2_with_one_line(
    drives_as_can: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``daror console --script`` runs lock-step: on a backend that drives hardware it is refused, nothing written."""
    assert isinstance(open_hal(hal_config("can")), StandInDrives)
    script = tmp_path / "s.txt"
    script.write_text("expect state startup\n", encoding="utf-8")
    out = tmp_path / "session"
    capsys.readouterr()
    code = main(["console", "--hal", "can", "--script", str(script), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.splitlines() == [f"daror console: error: {REFUSAL}"]
    assert not out.exists()


def test_console_script_with_sim_lines_on_hardware_exits_2_with_one_line(
    drives_as_can: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    script = tmp_path / "s.txt"
    script.write_text("expect state startup\nsim estop operator on\n", encoding="utf-8")
    out = tmp_path / "session"
    capsys.readouterr()
    code = main(["console", "--hal", "can", "--realtime", "--script", str(script), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.splitlines()) == 1
    assert "line 2" in err
    assert "'sim' acts on the simulated plant; this session runs on hardware" in err
    assert not out.exists()
