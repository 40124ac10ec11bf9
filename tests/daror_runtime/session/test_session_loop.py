"""Whole sessions through :class:`daror_runtime.runtime.Runtime` on the simulated plant (lock-step).

* a full session, start to compensation, with the real identification protocol, training and
  validation of PLF+, e-stop tests and the support it then delivers;
* every fault class provoked in every state where it can occur: what the FSM does with it in
  the tick it appears (FAIL, or the evidence of a test state), torque off, the audit log, and the
  only way back (condition gone, acknowledged, reset to startup);
* requests take effect at tick boundaries only, in the order posted;
* a bad spec, or a spec whose mode has no controller, stops the runtime from starting.

The detection of each fault class is tested in ``tests/daror_runtime/safety/test_safety_loop.py``; here it is only
provoked, the same ways (a limit narrowed below the present reading, the sim's sensor, drive and
bus faults, a pressed e-stop, a controller that raises, a clock that reports overruns).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from daror_runtime.clocks import LockStepClock, TickTiming
from daror_runtime.console.world import SimWorld
from daror_runtime.data.load import RAW_LOG_SUFFIX, load_stationary, raw_log_path, write_dataset
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import ConfigurationError
from daror_runtime.fsm.machine import Outcome
from daror_runtime.fsm.modes import MODES, ModeInfo
from daror_runtime.fsm.signals import EstopButton
from daror_runtime.fsm.spec import DEFAULT_SPEC_PATH, FsmSpecError, StateSpec, load_fsm_spec
from daror_runtime.fsm.supervisor import FsmSupervisor, Response, Ticket
from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.logs import configure_logging, flush_logs
from daror_runtime.loop import TickResult
from daror_runtime.models.files import save_model, training_summary
from daror_runtime.models.registry import fit_model, installation_options
from daror_runtime.runtime import Runtime
from daror_runtime.safety.faults import Fault, FaultKind
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor
from daror_runtime.session.settings import SessionSettings
from daror_runtime.testing import session_core
from hal.errors import HalError
from hal.interface import DriveState
from hal.isb import AngleRange, IsbLimits
from hal.robot import FloatArray
from hal.sim.backend import SimHal
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary
from tests.conftest import recorded_by_an_earlier_session
from tests.provoke import fail_next_read_as_bus_off

SCENARIO = "exo_dummy_arm"
SPEC = load_fsm_spec()
STATE_NAMES = [s.name for s in SPEC.states]
FAIL = SPEC.fail.name
TEST_STATE_WARNING = "fault in an e-stop test state: met by its reaction until acknowledged, no FAIL"

#: The smallest identification protocol that still trains a validated PLF+. Measured on this
#: scenario with the default ISB limits: every stride tried (3, 6, 10-20; 20 is the settings'
#: maximum) trains a validated PLF+ (validation RMSE 0.32-0.43 Nm against the limit of 1.5 Nm);
#: stride 12 (7 of the 83 waypoints) is the shortest in robot time (about 57 s training and 44 s
#: validation run, ~10 s of wall-clock time). Stride 20 has fewer waypoints (5) but longer moves.
FULL_SESSION_STRIDE = 12


# --- the audit log --------------------------------------------------------------------------


class AuditLog:
    """The JSON audit file of this module's sessions; :meth:`mark` then :meth:`since` picks one episode."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def _lines(self) -> list[str]:
        flush_logs()
        return self.path.read_text(encoding="utf-8").splitlines() if self.path.exists() else []

    def mark(self) -> int:
        return len(self._lines())

    def since(self, mark: int, session_id: str) -> list[dict[str, Any]]:
        events = [json.loads(line) for line in self._lines()[mark:]]
        return [e for e in events if e.get("session_id") == session_id]

    def all(self, session_id: str) -> list[dict[str, Any]]:
        return self.since(0, session_id)


@pytest.fixture(scope="module")
def audit(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AuditLog]:
    path = tmp_path_factory.mktemp("audit") / "audit.jsonl"
    configure_logging("critical", json_path=path, json_level="info")
    yield AuditLog(path)
    configure_logging()


def named(events: list[dict[str, Any]], event: str, **fields: Any) -> list[dict[str, Any]]:
    return [e for e in events if e["event"] == event and all(e.get(k) == v for k, v in fields.items())]


# --- a validated model for sessions that skip identification ----------------------------------


@dataclass(frozen=True)
class ModelFiles:
    model: Path
    validation: Path


def _dataset(points: Any) -> StationaryDataset:
    return StationaryDataset(points.q_rad, points.tau_nm, points.direction, points.t_s)


@pytest.fixture(scope="module")
def model_files(tmp_path_factory: pytest.TempPathFactory) -> ModelFiles:
    """PLF+ fitted on the scenario's simulated training set; its validation set beside it."""
    folder = tmp_path_factory.mktemp("model")
    scenario = load_scenario(SCENARIO)
    training = _dataset(generate_stationary(scenario, "training"))
    files = ModelFiles(folder / "plf_plus.json", folder / "validation.csv")
    write_dataset(files.validation, _dataset(generate_stationary(scenario, "validation")))
    recorded_by_an_earlier_session(files.validation, scenario, "validation")
    result = fit_model("plf+", training, scenario.description(), installation_options("plf+", dummy_arm=True))
    save_model(files.model, result.model, training_summary(training))
    return files


# --- simulated world helpers ----------------------------------------------------------------


class OverrunClock(LockStepClock):
    """Lock-step time whose ticks can be made to miss their deadline, as a real-time clock reports it."""

    def __init__(self, period_s: float) -> None:
        super().__init__(period_s)
        self.overrunning = False
        self._run = 0

    def wait(self) -> TickTiming:
        timing = super().wait()
        if not self.overrunning:
            self._run = 0
            return timing
        self._run += 1
        return timing._replace(lateness_s=1.5 * self.period_s, overrun=True, consecutive_overruns=self._run)


def torque_off(result: TickResult, hal: SimHal) -> bool:
    """The command written is torque-off and the simulated drives applied no torque in that tick."""
    return (
        result.command.enable is False
        and bool(np.all(result.command.motor_torque_nm == 0.0))
        and bool(np.all(hal.applied_motor_torque_nm == 0.0))
    )


_RANK = {"hold": 0, "lower": 1, "off": 2}


def expected_reaction(state: StateSpec, faults: list[Fault], drives: tuple[DriveState, ...]) -> tuple[str, set[int]]:
    """What ``fsm_spec.yaml`` declares for ``faults`` in ``state``: the reaction and the joints off.

    Restated from the spec (docs/safety.md), independently of daror_runtime.safety.reactions: the
    strictest reaction of any fault kind (its state override first); the joint a drive, torque-path or
    sensor fault names off (every joint when it names none); a joint whose drive held nothing off; an
    e-stop on the DAROR-01's safe-torque-off wiring off; no joint left: off.
    """
    reaction = "hold"
    off = {j + 1 for j, d in enumerate(drives) if d != DriveState.ENABLED}
    for fault in faults:
        entry = SPEC.fault_reactions[fault.kind]
        wanted = entry.states.get(state.name, entry.reaction)
        if fault.kind == FaultKind.ESTOP:
            wanted = "off"  # hal/daror01.yaml: estop.wiring sto
        reaction = max(reaction, wanted, key=_RANK.__getitem__)
        if entry.faulted_joint == "off":
            off |= {fault.joint} if fault.joint is not None else {1, 2, 3, 4}
    return ("off" if len(off) == 4 else reaction), off


def assert_reaction(result: TickResult, hal: SimHal, reaction: str, off: set[int]) -> None:
    """The tick's command and what the drives applied are the declared reaction's: torque off, or the
    joints off disabled (no torque applied) while the others keep their drives enabled and torque."""
    if reaction == "off":
        assert torque_off(result, hal), result.command
        return
    command = result.command
    assert command.enable is True, command
    assert set(command.joints_off) == off, (command.joints_off, off)
    applied = hal.applied_motor_torque_nm
    for j in off:
        assert applied[j - 1] == 0.0, applied
    driven = [j - 1 for j in range(1, 5) if j not in off]
    assert np.any(applied[driven] != 0.0), applied  # the held joints carry the arm


def release_the_arm(session: Session, keep: Callable[[], None] | None = None, seconds: float = 4.0) -> None:
    """A reaction holds the arm: the operator releases it (someone holds it) and the torque ramps out."""
    runtime = session.runtime
    if not runtime.arm_held:
        return
    accepted(session.answer(runtime.release_arm(), keep))
    for _ in range(round(seconds * 1000)):
        if not runtime.arm_held:
            return
        session.tick(1, keep)
    raise AssertionError("the arm is still held after the release")


def accepted(response: Response) -> Response:
    assert response.accepted, f"{response.request} refused in {response.state}: {response.reason}"
    return response


# --- a session that can be walked to any state ----------------------------------------------


class Session:
    """A runtime on the simulated plant with the world's pilot, an overrun clock and a validated model.

    The model is selected once (it outlives resets), so states 8 and 9 are passed without
    running the protocol (guard ``identification_data_or_model``).
    """

    def __init__(self, directory: Path, model: ModelFiles) -> None:
        self.clock = OverrunClock(1e-3)
        self.hal = SimHal(SCENARIO)
        self.runtime = Runtime(self.hal, directory, settings=SessionSettings(dummy_arm=True), clock=self.clock)
        self.visited: list[str] = []
        session_core(self.runtime).supervisor.listeners.append(lambda state, outcome: self.visited.append(state.name))
        self.runtime.open()
        self.world = SimWorld(self.hal.world)  # its pilot carries what the robot does not: relaxes onto support
        self.healthy = True
        runtime = self.runtime
        runtime.runner.run_ticks(1)
        runtime.select_model(model.model, model.validation)
        assert runtime.runner.run_until(
            lambda: runtime.model_in_use is not None and not session_core(runtime).jobs.pending, 1.0
        )
        assert runtime.model_in_use is not None
        assert runtime.model_in_use.validated

    @property
    def state(self) -> str:
        return self.runtime.state_name

    def tick(self, n: int = 1, keep: Callable[[], None] | None = None) -> TickResult:
        result = None
        for _ in range(n):
            if keep is not None:
                keep()
            result = self.runtime.runner.run_ticks(1)
        assert result is not None
        return result

    def answer(self, ticket: Ticket, keep: Callable[[], None] | None = None) -> Response:
        """Tick (keeping a fault's condition up) until the request was applied: the next tick."""
        self.tick(1, keep)
        assert ticket.response is not None, f"{ticket.request} not applied in the next tick"
        return ticket.response

    def press(self, button: str, ticks: int = 2) -> None:
        self.world.estop(button, True)
        self.tick(ticks)
        self.world.estop(button, False)
        self.tick(2)

    def walk_to(self, name: str, settle_ticks: int = 150) -> None:
        """Advance from the present state (startup after a reset) to ``name``, with each state's evidence."""
        runtime = self.runtime
        target = STATE_NAMES.index(name)
        assert self.state in STATE_NAMES, self.state
        assert STATE_NAMES.index(self.state) <= target, self.state
        while self.state != name:
            here = self.state
            if here == "safety_check":
                self.press("operator")
                self.press("pilot")
            elif here == "settings":
                accepted(self.answer(runtime.confirm("settings")))
            elif here == "pilot_installation":
                accepted(self.answer(runtime.confirm("installation")))
            elif here == "safety_experience":
                self.press("pilot")
                accepted(self.answer(runtime.confirm("safety_experience")))
            elif here == "rom_limits":
                accepted(self.answer(runtime.set_isb_limits(IsbLimits())))
            elif here == "operative_check":
                self.press("operator")
            elif here == "identification":
                self._advance_at_rest()
                continue
            accepted(self.answer(runtime.advance()))
            self.tick(settle_ticks)
        assert not session_core(runtime).monitor.faulted, session_core(runtime).monitor.latched

    def _advance_at_rest(self, settle_ticks: int = 150) -> None:
        """Advance out of ``identification``, which needs the robot at rest in the tick that decides.

        Sensor noise keeps the held arm's speed near the at-rest threshold, so an advance sent in a
        tick at rest may be decided in one that is not; it is refused for exactly that and sent again.
        """
        runtime = self.runtime
        for _ in range(50):
            assert runtime.runner.run_until(lambda: runtime.at_rest, 5.0), "the robot did not come to rest"
            response = self.answer(runtime.advance())
            if response.accepted:
                self.tick(settle_ticks)
                return
            assert response.unmet == ("robot_at_rest",), response
        raise AssertionError("identification: no advance at rest in 50 tries")

    def close(self) -> None:
        self.runtime.close()


# --- fault conditions -----------------------------------------------------------------------


class Condition:
    """The cause of one fault class in the world: started, kept up before every tick, cleared.

    ``persists``: the monitor sees whether the condition is still there (so FAIL's
    ``faults_cleared`` guard can be shown to wait for it); one-sample faults and faults reported
    outside the check (HAL, overrun, software) have no such persisting condition.
    """

    kind: FaultKind
    persists = True
    recurs_on_clear = False  # clearing it brings the fault back once (a new occurrence in FAIL)

    def __init__(self, session: Session) -> None:
        self.s = session

    def start(self) -> None:
        raise NotImplementedError

    def keep(self) -> None:
        """Called before each tick while the condition is to persist."""

    def clear(self) -> None:
        raise NotImplementedError


#: A limit no reading can meet, not even the exact zero of a quantised encoder: the stand-in for
#: a joint that keeps moving too fast, a spring that stays loaded, ...
BELOW_ANY_READING = -1e-9


class NarrowedLimit(Condition):
    """One limit of the monitor narrowed below the present reading (issue-3 style provocation).

    Entering FAIL restores the device limits, so while the condition is to persist, :meth:`keep`
    narrows them again (the joint is still out of range); :meth:`clear` restores them.
    """

    def __init__(self, session: Session, kind: FaultKind) -> None:
        super().__init__(session)
        self.kind = kind
        self.base: SafetyLimits | None = None
        self.narrowed: SafetyLimits | None = None

    def _narrow(self, limits: SafetyLimits) -> SafetyLimits:
        sample = self.s.runtime.last_sample
        assert sample is not None
        if self.kind == FaultKind.JOINT_LIMIT:
            upper = np.array(limits.joint_upper_rad, dtype=float)
            upper[3] = sample.q_rad[3] - 0.02  # the elbow is 20 mrad beyond its (new) upper limit
            return dataclasses.replace(limits, joint_upper_rad=upper)
        if self.kind == FaultKind.ISB_LIMIT:
            elbow_deg = float(np.degrees(sample.q_rad[3]))  # the ISB elbow angle is q4
            isb = IsbLimits(elbow=AngleRange(lower_deg=elbow_deg - 30.0, upper_deg=elbow_deg - 2.0))
            return limits.with_isb(isb, 0.0)
        if self.kind == FaultKind.VELOCITY:
            return dataclasses.replace(limits, max_velocity_rad_s=np.full(4, BELOW_ANY_READING))
        if self.kind == FaultKind.TORQUE:
            return dataclasses.replace(limits, max_spring_torque_nm=np.full(4, BELOW_ANY_READING))
        assert self.kind == FaultKind.DEFLECTION
        return dataclasses.replace(limits, max_deflection_rad=BELOW_ANY_READING)

    def _apply(self) -> None:
        monitor = session_core(self.s.runtime).monitor
        self.base = monitor.limits
        self.narrowed = self._narrow(self.base)
        monitor.set_limits(self.narrowed)

    def start(self) -> None:
        self._apply()

    def keep(self) -> None:
        if session_core(self.s.runtime).monitor.limits is not self.narrowed:  # a state change replaced them
            self._apply()

    def clear(self) -> None:
        monitor = session_core(self.s.runtime).monitor
        if monitor.limits is self.narrowed and self.base is not None:
            monitor.set_limits(self.base)


class NotFinite(Condition):
    kind = FaultKind.NOT_FINITE

    def start(self) -> None:
        self.s.hal.inject_fault("nan", 2)

    keep = start  # a sensor that keeps reading NaN

    def clear(self) -> None:
        self.s.hal.clear_faults()


class Jump(Condition):
    """A slipped encoder: the reading jumps once; its offset stays until cleared (one-sample fault)."""

    kind = FaultKind.JUMP
    persists = False
    recurs_on_clear = True

    def start(self) -> None:
        self.s.hal.inject_fault("jump", 3, 0.2)

    def clear(self) -> None:
        self.s.hal.clear_faults()  # the reading jumps back: a recurrence, before any acknowledgement


class Stale(Condition):
    kind = FaultKind.STALE

    def start(self) -> None:
        self.s.hal.inject_fault("stale", None, 100_000)

    def clear(self) -> None:
        self.s.hal.clear_faults()


class DriveFault(Condition):
    kind = FaultKind.DRIVE

    def start(self) -> None:
        self.s.hal.inject_fault("drive_fault", 2)

    def clear(self) -> None:
        self.s.hal.clear_faults()


class BusFault(Condition):
    kind = FaultKind.HAL
    persists = False

    def start(self) -> None:
        self.s.hal.inject_fault("bus")

    def clear(self) -> None:
        self.s.hal.clear_faults()


class BusOff(Condition):
    """The CAN bus's own fault (a read that fails as a bus-off controller's does, tests/provoke.py)."""

    kind = FaultKind.BUS
    persists = False

    def start(self) -> None:
        fail_next_read_as_bus_off(self.s.hal)

    def clear(self) -> None:
        self.s.hal.clear_faults()


class Estop(Condition):
    kind = FaultKind.ESTOP

    def start(self) -> None:
        self.s.world.estop("operator", True)

    def clear(self) -> None:
        self.s.world.estop("operator", False)


class Overrun(Condition):
    """Ticks that keep missing their deadline. Cleared right after the fault: the monitor cannot
    see an overrun persist (see :func:`test_fail_is_not_left_while_the_condition_persists`)."""

    kind = FaultKind.OVERRUN
    persists = False

    def start(self) -> None:
        self.s.clock.overrunning = True

    def clear(self) -> None:
        self.s.clock.overrunning = False


class SoftwareFault(Condition):
    """The state's controller raises; in a torque-off state (no controller runs) a request raises."""

    kind = FaultKind.SOFTWARE
    persists = False

    def __init__(self, session: Session) -> None:
        super().__init__(session)
        self.patched: Any = None

    def start(self) -> None:
        controller = session_core(self.s.runtime).supervisor.controller
        if controller is None:

            def buggy(supervisor: FsmSupervisor) -> Response:
                raise ZeroDivisionError("division by zero in a request")

            session_core(self.s.runtime).supervisor.post("buggy request", buggy)
            return

        def update(sample: Any, dt_s: float) -> Any:
            raise ZeroDivisionError("division by zero in a gain schedule")

        controller.update = update  # the instance attribute shadows the method
        self.patched = controller

    def clear(self) -> None:
        if self.patched is not None:
            del self.patched.update
            self.patched = None


CONDITIONS: dict[FaultKind, Callable[[Session], Condition]] = {
    FaultKind.JOINT_LIMIT: lambda s: NarrowedLimit(s, FaultKind.JOINT_LIMIT),
    FaultKind.ISB_LIMIT: lambda s: NarrowedLimit(s, FaultKind.ISB_LIMIT),
    FaultKind.VELOCITY: lambda s: NarrowedLimit(s, FaultKind.VELOCITY),
    FaultKind.TORQUE: lambda s: NarrowedLimit(s, FaultKind.TORQUE),
    FaultKind.DEFLECTION: lambda s: NarrowedLimit(s, FaultKind.DEFLECTION),
    FaultKind.NOT_FINITE: NotFinite,
    FaultKind.JUMP: Jump,
    FaultKind.STALE: Stale,
    FaultKind.ESTOP: Estop,
    FaultKind.OVERRUN: Overrun,
    FaultKind.DRIVE: DriveFault,
    FaultKind.HAL: BusFault,
    FaultKind.BUS: BusOff,
    FaultKind.SOFTWARE: SoftwareFault,
}


def not_applicable(state: StateSpec, kind: FaultKind) -> str | None:
    """Why ``kind`` cannot occur in ``state`` (None: it can).

    Every other class can occur in every state: the monitor checks every sample, the e-stops, the
    drives and the bus in every state, and the loop counts overruns in every state; a software
    fault in a torque-off state (1, 3: no controller runs) comes from a request that raises.
    """
    if kind == FaultKind.ISB_LIMIT and not state.enforce_isb:
        return (
            f"{state.name} does not enforce the pilot's ISB limits (enforce_isb: false): "
            "the monitor checks no ISB angles there"
        )
    return None


def _fault_cases() -> list[Any]:
    """Every (state, fault class) that can occur; the others are checked not to apply (test below)."""
    return [
        pytest.param(state.name, kind, id=f"{state.number}-{state.name}-{kind.value}")
        for state in SPEC.states
        for kind in FaultKind
        if not not_applicable(state, kind)
    ]


@pytest.mark.slow
def test_the_fault_classes_left_out_cannot_occur_there(sessions: Callable[[str], Session]) -> None:
    """isb_limit is left out exactly where the state does not enforce the ISB limits: the monitor has none there."""
    left_out = [(s.name, k) for s in SPEC.states for k in FaultKind if not_applicable(s, k)]
    assert left_out == [(s.name, FaultKind.ISB_LIMIT) for s in SPEC.states if not s.enforce_isb]
    for name, _ in left_out:
        assert session_core(sessions(name).runtime).monitor.limits.isb is None, f"{name} enforces ISB limits after all"


@pytest.fixture(scope="module")
def sessions(tmp_path_factory: pytest.TempPathFactory, model_files: ModelFiles) -> Iterator[Callable[[str], Session]]:
    """One session per state, reused by every fault class of that state (walked back after each reset).

    A session left unhealthy by a failed test is replaced by a new one.
    """
    by_state: dict[str, Session] = {}

    def ready(name: str) -> Session:
        session = by_state.get(name)
        if session is None or not session.healthy:
            if session is not None:
                session.close()
            session = by_state[name] = Session(tmp_path_factory.mktemp(f"session_{name}"), model_files)
        session.healthy = False  # until the test says otherwise
        session.walk_to(name)
        return session

    yield ready
    for session in by_state.values():
        session.close()


def provoke(session: Session, condition: Condition, max_ticks: int = 20) -> tuple[TickResult, list[Fault]]:
    """Start the condition and tick until a fault is latched; that tick's result and its new faults.

    A fault the supervisor itself reports inside the tick (a request that raised) is latched and
    routed in that tick but missing from ``TickResult.faults``
    (:func:`test_a_fault_reported_inside_the_supervisor_is_in_the_tick_result`), so the monitor is asked too.
    """
    condition.start()
    monitor = session_core(session.runtime).monitor
    for _ in range(max_ticks):
        result = session.tick(1, condition.keep)
        if result.faults or monitor.faulted:
            return result, result.faults or monitor.latched
    raise AssertionError(f"no fault in {max_ticks} ticks after provoking {condition.kind.value}")


def settle_until_clearable(session: Session, max_ticks: int = 200) -> None:
    monitor = session_core(session.runtime).monitor
    for _ in range(max_ticks):
        session.tick()
        if monitor.clearable:
            return
    raise AssertionError(f"fault conditions still present: {monitor.conditions_present()}")


# --- 1a: a full session ---------------------------------------------------------------------


@pytest.mark.slow
def test_full_session_start_to_compensation(tmp_path: Path, audit: AuditLog, monkeypatch: pytest.MonkeyPatch) -> None:
    settings = SessionSettings(
        dummy_arm=True, identification=IdentificationSettings(waypoint_stride=FULL_SESSION_STRIDE)
    )
    hal = SimHal(SCENARIO)
    runtime = Runtime(hal, tmp_path / "session", settings=settings)
    visited: list[tuple[str, str]] = []

    def record(state: Any, outcome: Outcome) -> None:
        visited.append((outcome.event.value, state.name))

    session_core(runtime).supervisor.listeners.append(record)
    # Every tick of the session: whenever an e-stop is pressed, no torque is written or applied.
    pressed_ticks: list[tuple[float, bool]] = []
    tick = session_core(runtime).loop.tick

    def observed_tick() -> TickResult:
        result = tick()
        if result.sample is not None and True in result.sample.estop:
            pressed_ticks.append((result.sample.t_s, torque_off(result, hal)))
        return result

    monkeypatch.setattr(session_core(runtime).loop, "tick", observed_tick)

    def ok(ticket: Ticket) -> Response:
        return accepted(runtime.wait(ticket))

    def press(button: str, seconds: float = 0.1) -> None:
        world.estop(button, True)
        runtime.runner.pass_time(seconds)
        world.estop(button, False)
        runtime.runner.pass_time(0.3)

    runtime.open()
    try:
        world = SimWorld(hal.world)
        # 1 startup
        runtime.runner.pass_time(0.2)
        ok(runtime.advance())
        # 2 safety_check: advance needs both e-stop tests
        refused = runtime.wait(runtime.advance())
        assert not refused.accepted
        assert refused.unmet == ("estop_operator_tested", "estop_pilot_tested")
        press("operator")
        press("pilot")
        assert session_core(runtime).signals.estop_tested == {EstopButton.OPERATOR, EstopButton.PILOT}
        ok(runtime.advance())
        # 3 settings, 4 pilot_installation
        ok(runtime.confirm("settings"))
        ok(runtime.advance())
        runtime.runner.pass_time(0.5)
        ok(runtime.confirm("installation"))
        ok(runtime.advance())
        # 5 safety_experience: the pilot's e-stop
        press("pilot")
        assert session_core(runtime).signals.estop_tested == {EstopButton.PILOT}
        ok(runtime.confirm("safety_experience"))
        ok(runtime.advance())
        # 6 rom_limits: the default limits contain every shipped waypoint; no validated model yet, so
        # operative_check needs the operator's approval of the A Priori model
        ok(runtime.set_isb_limits(IsbLimits()))
        refused = runtime.wait(runtime.advance())
        assert refused.unmet == ("compensation_model_approved",)
        ok(runtime.confirm("a_priori_model"))
        ok(runtime.advance())
        # 7 operative_check: the pilot relaxes onto the a priori compensation, then an e-stop under support
        world.pilot_carries(0.0)
        runtime.runner.pass_time(2.0)
        press("operator")
        assert session_core(runtime).signals.estop_tested == {EstopButton.OPERATOR}
        runtime.runner.pass_time(1.0)
        ok(runtime.advance())
        # 8 identification: the pilot goes limp, the protocol runs inside the limits
        world.pilot_stiffness(0.0)
        points = {}
        for kind in ("training", "validation"):
            ok(runtime.identify(kind))
            assert runtime.runner.run_until(lambda: not runtime.busy, 600.0), f"the {kind} run did not finish"
            assert session_core(runtime).progress.last_error is None, session_core(runtime).progress.last_error
            last = session_core(runtime).progress.last_identification
            assert last is not None
            assert last["kind"] == kind
            points[kind] = last["points"]
        ok(runtime.advance())
        # 9 training: PLF+ on this session's data
        trained = runtime.wait(runtime.train(), 60.0)
        assert trained.accepted, trained
        assert trained.request == "train plf+"
        assert runtime.model_in_use is trained.detail
        assert runtime.runner.run_until(lambda: not session_core(runtime).jobs.pending, 1.0)
        ok(runtime.advance())
        # 10 compensation: the support ramps to the operator's level
        world.pilot_stiffness(1.0)
        world.pilot_hold_here()
        compensation = session_core(runtime).modes.compensation
        for level in (0.6, 1.0):
            ok(runtime.set_support(level))
            assert runtime.runner.run_until(lambda: compensation.delivered_support_level == level, 3.0), level  # noqa: B023
            assert runtime.status()["delivered_support_level"] == level
        runtime.runner.pass_time(1.0)
        holding, residual = support_figures(runtime, world)
        status = runtime.status()
    finally:
        runtime.close()

    assert visited == [("advance", name) for name in STATE_NAMES[1:]]
    assert status["state"] == "compensation"
    # identification data: both datasets and their raw logs written, with stationary points
    saved = status["identification_saved"]
    assert set(saved) == {"training", "validation"}
    for kind, path in saved.items():
        assert Path(path).is_file()
        assert raw_log_path(path, RAW_LOG_SUFFIX).is_file()
        assert len(load_stationary(path)) == points[kind] > 0
    # the model: PLF+ trained on them, validated within the session's limit
    model = status["model"]
    assert model["kind"] == "plf+"
    assert model["validated"] is True
    assert 0.0 < model["validation_rmse_nm"] <= settings.max_validation_rmse_nm
    assert Path(model["path"]).is_file()
    # e-stops: pressed four times for 0.1 s, torque off in every pressed tick, recorded as the tests
    assert len(pressed_ticks) == 4 * 100
    assert all(off for _, off in pressed_ticks), [t for t, off in pressed_ticks if not off][:5]
    events = audit.all(status["session_id"])
    tests = [(e["state"], e["buttons"]) for e in named(events, "e-stop test")]
    assert tests == [
        ("safety_check", ["operator"]),
        ("safety_check", ["pilot"]),
        ("safety_experience", ["pilot"]),
        ("operative_check", ["operator"]),
    ]
    assert named(events, "transition", dest=FAIL) == []
    assert {e["kind"] for e in named(events, "fault") if "kind" in e} == {"estop"}  # no other fault, ever
    # the robot carries the arm: what the relaxed pilot still adds is far below the arm's holding torque
    assert np.all(holding > 0.5), holding
    assert np.all(residual < 0.1 * holding), (residual, holding)


def support_figures(runtime: Runtime, world: SimWorld, seconds: float = 2.0) -> tuple[FloatArray, FloatArray]:
    """Mean |holding torque| of the arm and RMS of the relaxed pilot's torque, per joint (as rehearsal.py)."""
    holding: list[FloatArray] = []
    pilot: list[FloatArray] = []

    def sample(result: TickResult) -> bool:
        holding_nm, pilot_nm = world.support_torques()
        holding.append(np.abs(holding_nm))
        pilot.append(pilot_nm)
        return False

    assert world.pilot_carried == 0.0
    runtime.runner.run_ticks(round(seconds * runtime.rate_hz), stop=sample)
    return np.mean(holding, axis=0), np.sqrt(np.mean(np.square(pilot), axis=0))


# --- 1b: every fault class in every state ----------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(("state_name", "kind"), _fault_cases())
def test_fault_in_state(state_name: str, kind: FaultKind, sessions: Callable[[str], Session], audit: AuditLog) -> None:
    session = sessions(state_name)
    state = SPEC.state(state_name)
    condition = CONDITIONS[kind](session)
    mark = audit.mark()
    before = list(session.visited)
    try:
        if state.fail_on_fault:
            _fault_fails_the_state(session, state, condition, audit, mark)
        else:
            _fault_in_a_test_state(session, state, condition, audit, mark)
            assert session.visited == before, "a test state changed state on a fault"
    finally:
        condition.clear()
    session.healthy = True


def _fault_fails_the_state(
    session: Session, state: StateSpec, condition: Condition, audit: AuditLog, mark: int
) -> None:
    runtime = session.runtime
    kind = condition.kind
    before = runtime.last_sample
    assert before is not None
    result, new = provoke(session, condition)
    # the tick the fault appears in: FAIL, and the reaction the spec declares (torque off, or the arm held)
    assert kind in {f.kind for f in new}, new
    assert session.state == FAIL
    assert session.visited[-1] == FAIL
    # the drives as the tick that found the fault read them (no reading that tick: as the tick before)
    reaction, off = expected_reaction(state, new, (result.sample or before).drives)
    assert_reaction(result, session.hal, reaction, off)
    if not condition.persists:
        condition.clear()
    events = audit.since(mark, runtime.session_id)
    faults = named(events, "fault", state=state.name)
    assert len(faults) == 1, faults
    assert kind.value in [f["kind"] for f in faults[0]["faults"]], faults
    to_fail = named(events, "transition", dest=FAIL)
    assert len(to_fail) == 1
    assert to_fail[0]["source"] == state.name
    assert to_fail[0]["trigger"] == "fail"
    assert to_fail[0]["t_s"] == faults[0]["t_s"] == new[0].t_s  # the same tick
    reactions = named(events, "reaction")
    assert len(reactions) == 1, reactions
    assert reactions[0]["reaction"] == reaction
    assert reactions[0]["t_s"] == new[0].t_s
    for _ in range(3):  # FAIL keeps the reaction: torque off, or the arm held
        assert_reaction(session.tick(1, condition.keep), session.hal, reaction, off)
    if reaction != "off":  # a reset would drop an arm the reaction holds: refused until released
        refusal = session.answer(runtime.reset(), condition.keep)
        assert not refusal.accepted
        assert "arm_released" in refusal.unmet
        release_the_arm(session, condition.keep)
        assert torque_off(session.tick(1, condition.keep), session.hal)
    if condition.persists:
        # reset waits for both; the acknowledgement may come first, the reset still waits for the condition
        refusal = session.answer(runtime.reset(), condition.keep)
        assert not refusal.accepted
        assert refusal.unmet == ("faults_cleared", "fault_acknowledged")
        accepted(session.answer(runtime.acknowledge(), condition.keep))
        assert kind in session_core(runtime).monitor.conditions_present()
        refusal = session.answer(runtime.reset(), condition.keep)
        assert not refusal.accepted
        assert refusal.unmet == ("faults_cleared",)
        assert session.state == FAIL
        condition.clear()
        settle_until_clearable(session)
        assert session_core(runtime).signals.fault_acknowledged, "a new fault appeared while the condition was cleared"
    else:
        # a one-sample fault (cleared above): the condition is gone, the acknowledgement is missing
        settle_until_clearable(session)
        recurred = [
            e for e in named(audit.since(mark, runtime.session_id), "fault in FAIL") if kind.value in str(e["faults"])
        ]
        assert len(recurred) == (1 if condition.recurs_on_clear else 0), recurred
        refusal = session.answer(runtime.reset())
        assert not refusal.accepted
        assert refusal.unmet == ("fault_acknowledged",)
        assert session.state == FAIL
        accepted(session.answer(runtime.acknowledge()))
    assert session.state == FAIL
    assert session_core(runtime).monitor.faulted
    # both done: reset leaves FAIL for startup, with nothing latched
    back = accepted(session.answer(runtime.reset()))
    assert back.state == "startup" == session.state
    assert session.visited[-2:] == [FAIL, "startup"]
    assert not session_core(runtime).monitor.faulted
    assert torque_off(session.tick(), session.hal)  # startup: drives off
    events = audit.since(mark, runtime.session_id)
    refused = [e["unmet"] for e in named(events, "refused", request="reset")]
    if reaction != "off":  # the first reset was refused while the reaction held the arm
        assert "arm_released" in refused.pop(0)
    if condition.persists:
        assert refused == [["faults_cleared", "fault_acknowledged"], ["faults_cleared"]]
    else:
        assert refused == [["fault_acknowledged"]]
    assert named(events, "transition", source=FAIL, dest="startup", trigger="reset")


def _fault_in_a_test_state(
    session: Session, state: StateSpec, condition: Condition, audit: AuditLog, mark: int
) -> None:
    runtime = session.runtime
    kind = condition.kind
    before = runtime.last_sample
    assert before is not None
    result, new = provoke(session, condition)
    assert kind in {f.kind for f in new}, new
    assert session.state == state.name  # no FAIL in a test state
    # the drives as the tick that found the fault read them (no reading that tick: as the tick before)
    reaction, off = expected_reaction(state, new, (result.sample or before).drives)
    assert_reaction(result, session.hal, reaction, off)
    if not condition.persists:
        condition.clear()
    events = audit.since(mark, runtime.session_id)
    assert named(events, "transition") == []
    if kind == FaultKind.ESTOP:
        tests = named(events, "e-stop test", state=state.name)
        assert [e["buttons"] for e in tests] == [["operator"]]
        assert EstopButton.OPERATOR in session_core(runtime).signals.estop_tested
    else:
        warnings = named(events, TEST_STATE_WARNING, state=state.name)
        assert kind.value in [e["fault"]["kind"] for e in warnings], warnings
        assert warnings[0]["level"] == "warning"
    # the reaction lasts while the fault is latched
    for _ in range(5):
        held = session.tick(1, condition.keep)
        assert_reaction(held, session.hal, reaction, off)
        assert session.state == state.name
    if kind == FaultKind.ESTOP:
        # the press was the test: released, the latch clears by itself and torque returns
        condition.clear()
        back = session.tick(2)
        assert not session_core(runtime).monitor.faulted
        assert back.command.enable
        assert session.state == state.name
        return
    if condition.persists:
        accepted(session.answer(runtime.acknowledge(), condition.keep))
        assert kind in {f.kind for f in session_core(runtime).monitor.latched}, (
            "acknowledged away while the condition persists"
        )
        assert_reaction(session.tick(1, condition.keep), session.hal, reaction, off)
    condition.clear()
    settle_until_clearable(session)
    for _ in range(3):  # gone, but latched until acknowledged: the reaction goes on
        assert_reaction(session.tick(), session.hal, reaction, off)
    accepted(session.answer(runtime.acknowledge()))
    back = session.tick()
    assert not session_core(runtime).monitor.faulted
    assert back.command.enable
    assert session.state == state.name
    assert named(audit.since(mark, runtime.session_id), "test fault acknowledged", state=state.name)


# --- faults whose condition the monitor cannot see persist -----------------------------------


@pytest.fixture
def session_in_settings(tmp_path: Path, model_files: ModelFiles) -> Iterator[Session]:
    session = Session(tmp_path / "session", model_files)
    session.walk_to("settings")
    yield session
    session.close()


@pytest.mark.parametrize("kind", [FaultKind.OVERRUN, FaultKind.HAL])
def test_fail_is_not_left_while_the_condition_persists(session_in_settings: Session, kind: FaultKind) -> None:
    session = session_in_settings
    runtime = session.runtime

    def keep() -> None:  # the condition persists: every tick overruns / every read fails
        if kind == FaultKind.OVERRUN:
            session.clock.overrunning = True
        else:
            session.hal.inject_fault("bus")

    for _ in range(10):
        result = session.tick(1, keep)
        if result.faults:
            break
    assert session.state == FAIL
    assert kind in {f.kind for f in session_core(runtime).monitor.latched}
    accepted(session.answer(runtime.acknowledge(), keep))
    response = session.answer(runtime.reset(), keep)
    assert not response.accepted
    assert "faults_cleared" in response.unmet
    assert session.state == FAIL


@pytest.mark.slow
def test_acknowledging_an_overrun_in_a_test_state_keeps_its_reaction_while_it_persists(
    tmp_path: Path, model_files: ModelFiles
) -> None:
    """An overrun in safety_check: the spec's reaction (lower) holds the arm; acknowledging while the loop still
    overruns does not hand the robot back to the state's own controller."""
    session = Session(tmp_path / "session", model_files)
    try:
        session.walk_to("safety_check")
        before = session.runtime.last_sample
        session.clock.overrunning = True
        result, new = provoke(session, Overrun(session))
        assert session.state == "safety_check"
        reaction, off = expected_reaction(SPEC.state("safety_check"), new, (result.sample or before).drives)
        assert_reaction(result, session.hal, reaction, off)
        ticket = session.runtime.acknowledge()
        written = [session.tick() for _ in range(5)]
        assert ticket.response is not None
        assert ticket.response.accepted
        for r in written:  # the loop still overruns: still the reaction, not minimal impedance
            assert_reaction(r, session.hal, reaction, off)
        assert session_core(session.runtime).supervisor.reaction is not None
        assert (
            session_core(session.runtime).supervisor.controller
            is not session_core(session.runtime).modes.minimal_impedance
        )
    finally:
        session.clock.overrunning = False
        session.close()


# --- 1c: requests take effect at tick boundaries ---------------------------------------------


def test_requests_are_applied_at_the_next_tick_in_the_order_posted(
    tmp_path: Path, model_files: ModelFiles, audit: AuditLog
) -> None:
    session = Session(tmp_path / "session", model_files)
    runtime = session.runtime
    transitions: list[tuple[str, float]] = []
    session_core(runtime).supervisor.listeners.append(
        lambda state, outcome: transitions.append((state.name, runtime.last_sample.t_s))
    )
    try:
        session.walk_to("settings")
        # posted: nothing happens until a tick, however long the caller waits
        confirm, advance = runtime.confirm("settings"), runtime.advance()
        assert not confirm.done
        assert not advance.done
        assert session_core(runtime).supervisor.pending_requests
        assert runtime.busy
        assert session.state == "settings"
        assert session_core(runtime).signals.confirmed == set()
        # one tick: both applied, in order (the confirmation lets the advance through)
        mark = audit.mark()
        result = session_core(runtime).loop.tick()
        assert confirm.done
        assert advance.done
        assert not session_core(runtime).supervisor.pending_requests
        assert accepted(confirm.response).state == "settings"  # type: ignore[arg-type]
        assert accepted(advance.response).state == "pilot_installation"  # type: ignore[arg-type]
        assert transitions[-1] == ("pilot_installation", result.sample.t_s)
        events = audit.since(mark, runtime.session_id)
        order = [e["event"] for e in events if e["event"] in ("checklist confirmed", "transition")]
        assert order == ["checklist confirmed", "transition"]
        assert {e["t_s"] for e in events if "t_s" in e and e["event"] != "request"} == {result.sample.t_s}
        # the other order: the advance is decided before the confirmation exists
        accepted(session.answer(runtime.revert()))
        assert session.state == "settings"
        advance, confirm = runtime.advance(), runtime.confirm("settings")
        session_core(runtime).loop.tick()
        refused = advance.response
        assert refused is not None
        assert not refused.accepted
        assert refused.unmet == ("settings_confirmed",)
        assert accepted(confirm.response).state == "settings"  # type: ignore[arg-type]
        assert session.state == "settings"
        assert accepted(session.answer(runtime.advance())).state == "pilot_installation"
    finally:
        session.close()


# --- 1d: a bad spec, or a mode without a controller, stops the runtime --------------------------


def _spec_document() -> dict[str, Any]:
    return yaml.safe_load(DEFAULT_SPEC_PATH.read_text(encoding="utf-8"))


def _typo_guard(doc: dict[str, Any]) -> None:
    doc["states"][2]["guards"]["advance"][0] = "settings_confirmd"


def _estop_test_that_fails(doc: dict[str, Any]) -> None:
    doc["states"][1]["fail_on_fault"] = True


def _fail_without_acknowledgement(doc: dict[str, Any]) -> None:
    doc["fail"]["guards"]["reset"] = ["faults_cleared"]


def _unknown_mode(doc: dict[str, Any]) -> None:
    doc["states"][9]["mode"] = "assist"


def _numbering_gap(doc: dict[str, Any]) -> None:
    for state in doc["states"][4:]:
        state["number"] += 1


@pytest.mark.parametrize(
    ("mutate", "names"),
    [
        (_typo_guard, "states.2.guards.advance.0"),
        (_estop_test_that_fails, "states.1.fail_on_fault"),
        (_fail_without_acknowledgement, "fault_acknowledged"),
        (_unknown_mode, "states.9.mode"),
        (_numbering_gap, "states.4.number"),
    ],
)
def test_a_bad_spec_keeps_the_runtime_from_starting(
    tmp_path: Path, mutate: Callable[[dict[str, Any]], None], names: str
) -> None:
    doc = _spec_document()
    mutate(doc)
    bad = tmp_path / "bad_spec.yaml"
    bad.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    hal = SimHal(SCENARIO)
    session_dir = tmp_path / "session"
    with pytest.raises(FsmSpecError) as error:
        Runtime(hal, session_dir, spec=load_fsm_spec(bad))
    assert str(bad) in str(error.value)
    assert names in str(error.value)
    assert not session_dir.exists()
    with pytest.raises(HalError, match="not open"):
        hal.read()


def test_a_mode_without_a_controller_is_a_configuration_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    hal = SimHal(SCENARIO)
    runtime = Runtime(hal, tmp_path / "good")
    controllers = session_core(runtime).modes.by_mode()
    del controllers["hold"]
    with pytest.raises(ConfigurationError, match="hold"):
        FsmSupervisor(
            SPEC, SafetyMonitor(session_core(runtime).monitor.limits), session_core(runtime).monitor.limits, controllers
        )
    # a mode the registry knows (so the spec loads) but the runtime builds no controller for
    monkeypatch.setitem(MODES, "assist", ModeInfo("assist", "a new mode", applies_torque=True, pilot_driven=True))
    doc = _spec_document()
    _unknown_mode(doc)
    spec_path = tmp_path / "assist_spec.yaml"
    spec_path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    spec = load_fsm_spec(spec_path)
    assert spec.state("compensation").mode == "assist"
    session_dir = tmp_path / "session"
    with pytest.raises(ConfigurationError, match="assist"):
        Runtime(hal, session_dir, spec=spec)
    assert not session_dir.exists()


def test_a_fault_reported_inside_the_supervisor_is_in_the_tick_result(tmp_path: Path, model_files: ModelFiles) -> None:
    session = Session(tmp_path / "session", model_files)
    try:
        session.tick(10)
        condition = SoftwareFault(session)
        condition.start()  # startup runs no controller: a request raises
        result = session.tick()
        assert session.state == FAIL
        assert [f.kind for f in session_core(session.runtime).monitor.latched] == [FaultKind.SOFTWARE]
        assert [f.kind for f in result.faults] == [FaultKind.SOFTWARE]
    finally:
        session.close()
