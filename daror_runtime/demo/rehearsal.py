"""A full session on the simulated plant, start to compensation (the first part of ``daror demo``).

The console script ``daror_runtime/console/scripts/session.txt`` plays operator, pilot and
buttons through all ten states of ``fsm_spec.yaml``: e-stop tests, checklists, the pilot's range
of motion, the identification protocol inside it, training and validation of PLF+, and
compensation. Then the pilot relaxes and the demo measures what the robot carries: the torque
the pilot still has to add to hold the arm still, against the arm's full holding torque.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from daror_runtime.console.commands import ConsoleSession
from daror_runtime.console.grammar import check_lines
from daror_runtime.console.run import read_script, run_script
from daror_runtime.console.world import SimWorld
from daror_runtime.errors import DarorError
from daror_runtime.fsm.machine import Outcome
from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.loop import TickResult
from daror_runtime.runtime import Runtime
from daror_runtime.session.settings import SessionSettings
from hal.config import SimHalConfig
from hal.interface import open_hal

#: The demo's protocol: every third waypoint (28 of 83) keeps the demo near half a minute.
DEMO_SETTINGS = SessionSettings(dummy_arm=True, identification=IdentificationSettings(waypoint_stride=3))


def session_script() -> Path:
    """The packaged session script."""
    with resources.as_file(resources.files("daror_runtime.console") / "scripts" / "session.txt") as path:
        return Path(path)


@dataclass
class SessionReport:
    session_id: str
    final_state: str
    transitions: list[dict[str, Any]] = field(default_factory=list)
    status: dict[str, Any] = field(default_factory=dict)
    holding_torque_nm: list[float] = field(default_factory=list)  # what the arm needs (mean |g| per joint)
    unsupported_torque_nm: list[float] = field(default_factory=list)  # what the pilot still adds (RMS per joint)
    robot_time_s: float = 0.0

    def document(self) -> dict[str, Any]:
        return {
            "session_id": self.session_id,
            "final_state": self.final_state,
            "transitions": self.transitions,
            "robot_time_s": self.robot_time_s,
            "identification": self.status.get("identification_saved"),
            "model": self.status.get("model"),
            "isb_limits_deg": self.status.get("isb_limits"),
            "holding_torque_nm": self.holding_torque_nm,
            "unsupported_torque_nm": self.unsupported_torque_nm,
        }


def rehearse(directory: Path, console: Console, scenario_name: str = "exo_dummy_arm") -> SessionReport:
    """Run the session script on the simulated plant into ``directory``.

    Raises:
        ScriptCheckError: a step of the session did not happen (the message names the line).
    """
    hal = open_hal(SimHalConfig(scenario=scenario_name))
    runtime = Runtime(hal, directory, settings=DEMO_SETTINGS)
    transitions: list[dict[str, Any]] = []

    def record(state: Any, outcome: Outcome) -> None:
        sample = runtime.last_sample
        transitions.append(
            {
                "t_s": round(sample.t_s, 3) if sample is not None else None,
                "event": outcome.event.value,
                "from": outcome.source,
                "to": state.name,
            }
        )

    runtime.on_transition(record)
    runtime.open()
    try:
        world = SimWorld(runtime.world)
        session = ConsoleSession(runtime, console, world)
        script = session_script()
        run_script(session, script, check_lines(read_script(script), str(script), session.context))
        holding, unsupported = _support_figures(runtime, world)
        report = SessionReport(
            runtime.session_id,
            runtime.state_name,
            transitions,
            runtime.status(),
            holding,
            unsupported,
            world.t_s,
        )
    finally:
        runtime.shutdown("the rehearsal ended")
        runtime.close()
    if report.final_state != "compensation":
        raise DarorError(f"the session ended in {report.final_state}, not in compensation")
    return report


def _support_figures(runtime: Runtime, world: SimWorld, seconds: float = 2.0) -> tuple[list[float], list[float]]:
    """Over ``seconds`` of compensation with the pilot relaxed: mean |g(q)| and RMS of the pilot's torque, per joint."""
    holding: list[np.ndarray] = []
    pilot: list[np.ndarray] = []

    def sample(result: TickResult) -> bool:
        holding_nm, pilot_nm = world.support_torques()
        holding.append(np.abs(holding_nm))
        pilot.append(pilot_nm)
        return False

    runtime.runner.run_ticks(round(seconds * runtime.rate_hz), stop=sample)
    return (
        [float(v) for v in np.mean(holding, axis=0)],
        [float(v) for v in np.sqrt(np.mean(np.square(pilot), axis=0))],
    )
