"""Issue 28, part 2: the session knows its pilot (``pilot CODE`` in settings; needed on a real robot).

The code names the session in its status, ``session.json``, the audit trail and what it records; it
is named up to the state whose advance needs it, and on a robot that drives hardware that state is
not left without it (a simulated robot's pilot is its scenario's, so scripts run unchanged).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from daror_runtime.console.world import SimWorld
from daror_runtime.fsm.supervisor import Response, Ticket
from daror_runtime.logs import configure_logging, flush_logs
from daror_runtime.runtime import Runtime
from daror_runtime.session.core import RequestRefusedError
from daror_runtime.session.settings import SessionSettings
from daror_runtime.testing import session_core
from hal.sim.backend import SimHal


def _answer(runtime: Runtime, ticket: Ticket) -> Response:
    runtime.runner.run_ticks(1)
    assert ticket.response is not None
    return ticket.response


def _to_settings(runtime: Runtime) -> None:
    world = SimWorld(runtime.world)  # type: ignore[arg-type]
    runtime.runner.run_ticks(2)
    assert _answer(runtime, runtime.advance()).accepted
    for button in ("operator", "pilot"):
        world.estop(button, True)
        runtime.runner.run_ticks(3)
        world.estop(button, False)
        runtime.runner.run_ticks(3)
    assert _answer(runtime, runtime.advance()).accepted
    assert runtime.state_name == "settings"


@pytest.fixture
def runtime(tmp_path: Path) -> Runtime:
    runtime = Runtime(SimHal("exo_dummy_arm"), tmp_path / "session", settings=SessionSettings(dummy_arm=True))
    runtime.open()
    yield runtime
    runtime.close()


def test_a_simulated_session_s_pilot_is_its_scenario_s_until_named(runtime: Runtime, tmp_path: Path) -> None:
    audit = tmp_path / "audit.jsonl"
    configure_logging("critical", json_path=audit, json_level="info")
    try:
        assert runtime.snapshot().pilot == "simulated pilot (exo_dummy_arm)"
        _to_settings(runtime)
        assert _answer(runtime, runtime.name_pilot("P-007")).accepted
        assert runtime.snapshot().pilot == "P-007"
        assert _answer(runtime, runtime.confirm("settings")).accepted
        assert _answer(runtime, runtime.advance()).accepted
        refused = _answer(runtime, runtime.name_pilot("P-008"))  # the state that names him is left
        assert not refused.accepted
        assert (
            refused.reason
            == "the pilot is named before settings is left, not in pilot_installation; reset to name another"
        )
        runtime.shutdown("the test ended")
        runtime.close()
        flush_logs()
    finally:
        configure_logging()
    assert json.loads((tmp_path / "session" / "session.json").read_text(encoding="utf-8"))["pilot"] == "P-007"
    events = [json.loads(line) for line in audit.read_text(encoding="utf-8").splitlines()]
    named = [e for e in events if e["event"] == "pilot named"]
    assert len(named) == 1
    assert named[0]["pilot"] == "P-007"
    assert named[0]["previous"] is None
    after = events[events.index(named[0]) :]
    assert all(e.get("pilot") == "P-007" for e in after if e.get("session_id") == runtime.session_id)


def test_a_robot_that_drives_hardware_does_not_leave_settings_without_a_pilot(runtime: Runtime) -> None:
    _to_settings(runtime)
    session_core(runtime).signals.drives_hardware = True  # what a real robot's backend sets (hal.drives_hardware)
    assert runtime.snapshot().pilot == "simulated pilot (exo_dummy_arm)"  # the scenario still names a simulated one
    session_core(runtime).signals.pilot = None  # ... which a robot that drives hardware does not have
    assert _answer(runtime, runtime.confirm("settings")).accepted
    refused = _answer(runtime, runtime.advance())
    assert not refused.accepted
    assert refused.unmet == ("pilot_named",)
    assert _answer(runtime, runtime.name_pilot("P-007")).accepted
    assert _answer(runtime, runtime.advance()).accepted
    assert runtime.state_name == "pilot_installation"


def test_a_name_is_not_a_code(runtime: Runtime) -> None:
    for bad in ("Jean Dupont", "", "-x", "x" * 33, "P/007"):
        with pytest.raises(RequestRefusedError, match="not a code; expected letters, digits"):
            runtime.name_pilot(bad)
