"""Issue 24, defect 3: the robot does not enter the pilot's enforced ISB limits with the arm outside them.

`rom load pilot_isb.yaml` (elevation 10..70 deg), `confirm a_priori_model`, `advance` was accepted with
the arm at elevation 0 deg, and the next tick faulted ("isb_limit: elevation 0.0 deg beyond the pilot's
limit 5.0 deg"; the status showed 10..70, the 5 deg margin was not explained). Now the advance is refused
by the guard ``arm_inside_isb_limits`` naming the angle, how far it is outside and the margin; the next
steps tell the operator what to do; once the arm is inside, the advance is accepted without a fault.
Every ISB fault message names the recorded range and the margin it allowed.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from daror_runtime.console.commands import ConsoleSession
from daror_runtime.console.guide import next_steps
from daror_runtime.safety.faults import FaultKind
from daror_runtime.session.settings import RestSettings, SessionSettings
from daror_runtime.testing import session_core
from hal.isb import AngleRange, IsbLimits
from tests.daror_runtime.session.test_session_safety import Session

#: The lab engineer's file: a pilot who cannot lower his arm below 10 deg of elevation.
PILOT_ISB = IsbLimits(
    elevation=AngleRange(lower_deg=10.0, upper_deg=70.0),
    horizontal_rotation=AngleRange(lower_deg=-20.0, upper_deg=120.0),
    axial_rotation=AngleRange(lower_deg=-60.0, upper_deg=60.0),
    elbow=AngleRange(lower_deg=5.0, upper_deg=120.0),
)


@pytest.fixture
def lines(tmp_path: Path) -> Iterator[tuple[Session, ConsoleSession, io.StringIO]]:
    # the rest pose (where a fault lowers the arm) must lie inside the pilot's limits (issue 23)
    settings = SessionSettings(dummy_arm=True, rest=RestSettings(pose_isb_deg=(15.0, 0.0, 0.0, 30.0)))
    session = Session(tmp_path / "session", settings)
    buffer = io.StringIO()
    console = ConsoleSession(session.runtime, Console(file=buffer, width=400, color_system=None), session.world)
    yield session, console, buffer
    session.close()


def _isb_deg(session: Session) -> np.ndarray:
    return np.degrees(session.runtime.shoulder.isb_single(session.hal.truth().q_rad))


def test_the_advance_waits_until_the_arm_is_inside_the_limits(
    lines: tuple[Session, ConsoleSession, io.StringIO],
) -> None:
    session, console, buffer = lines
    runtime = session.runtime
    session.walk_to("rom_limits")
    assert _isb_deg(session)[0] < 5.0 - 1.0  # the arm hangs below the pilot's range minus the margin
    session.ok(runtime.set_isb_limits(PILOT_ISB))
    session.ok(runtime.confirm("a_priori_model"))
    response = runtime.wait(runtime.advance())
    assert not response.accepted
    assert response.unmet == ("arm_inside_isb_limits",)
    elevation = _isb_deg(session)[0]
    assert (
        f"elevation {elevation:.1f} deg is {10.0 - elevation:.1f} deg outside the pilot's recorded range "
        "10.0..70.0 deg (the monitor allows 5.0 deg beyond it: isb_margin_deg)"
    ) in response.reason
    runtime.runner.run_ticks(200)
    assert not session_core(runtime).monitor.faulted  # refused: nothing was entered, nothing faulted
    assert session.state == "rom_limits"
    # the next steps say what to do, with the figures
    status = runtime.snapshot()
    step = next_steps(status, True)[0]
    assert "outside his recorded ISB limits (elevation" in step.text
    assert "move the arm inside them" in step.text
    # the pilot raises his arm into his range (in the simulated world), then the advance is accepted
    console.execute("sim pilot move 40 30 0 60")
    assert "the pilot moves the arm to that pose until t =" in buffer.getvalue()
    assert runtime.runner.run_until(lambda: runtime.at_rest and _isb_deg(session)[0] > 35.0, 20.0)
    session.ok(runtime.advance())
    assert session.state == "operative_check"
    runtime.runner.pass_time(1.0)
    assert not session_core(runtime).monitor.faulted, session_core(runtime).monitor.latched


def test_an_isb_fault_names_the_recorded_range_and_the_margin(
    lines: tuple[Session, ConsoleSession, io.StringIO],
) -> None:
    """The monitor's own message, with the pilot's range narrowed just below the elbow's reading (5 deg margin)."""
    session, _, _ = lines
    runtime = session.runtime
    session.walk_to("rom_limits")
    session.world.pilot_move(runtime.shoulder.q_from_isb(np.radians([40.0, 30.0, 0.0, 60.0])))
    assert runtime.runner.run_until(lambda: runtime.at_rest and _isb_deg(session)[0] > 35.0, 20.0)
    session.ok(runtime.set_isb_limits(PILOT_ISB))
    session.ok(runtime.confirm("a_priori_model"))
    session.ok(runtime.advance())
    monitor = session_core(runtime).monitor
    elbow = _isb_deg(session)[3]
    narrowed = IsbLimits(elbow=AngleRange(lower_deg=elbow - 40.0, upper_deg=elbow - 8.0))
    monitor.set_limits(monitor.limits.with_isb(narrowed), session_core(runtime).signals.isb_angles(narrowed))
    runtime.runner.run_ticks(2)
    faults = [f for f in monitor.latched if f.kind == FaultKind.ISB_LIMIT]
    assert faults, monitor.latched
    message = faults[0].message
    value = float(message.split()[1])
    assert message == (
        f"elbow {value:.1f} deg is {value - (elbow - 8.0):.1f} deg outside the pilot's recorded range "
        f"{elbow - 40.0:.1f}..{elbow - 8.0:.1f} deg (the monitor allows 5.0 deg beyond it: isb_margin_deg)"
    )
    assert value - (elbow - 8.0) > 5.0


def test_a_sim_pilot_move_to_a_pose_the_robot_cannot_reach_is_one_line(
    lines: tuple[Session, ConsoleSession, io.StringIO],
) -> None:
    _, console, _ = lines
    from daror_runtime.console.grammar import CommandError

    with pytest.raises(CommandError, match=r"^sim pilot move: "):
        console.execute("sim pilot move 170 170 170 170")
