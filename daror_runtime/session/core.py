"""What a session is made of: the parts behind :class:`daror_runtime.runtime.Runtime`, wired once.

The runtime is a narrow facade (the operator's requests, a typed status, the loop's lifecycle);
everything it drives lives here, in one :class:`SessionCore` that the request handlers
(:mod:`.requests`) and the status (:mod:`.snapshot`) work on. Nothing outside ``session/`` and the
runtime reaches into it: the console talks to the facade only (tests/test_boundaries.py).

Threads: the core's parts are changed by the tick (the supervisor, the monitor, the signals, the
modes) and, between ticks, by request handlers that the supervisor applies at a tick boundary;
jobs (:mod:`.jobs`) hand their results back through such requests. Nothing here blocks the tick.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog

from daror_runtime.clocks import Clock, check_clock, clock_for
from daror_runtime.control.position import LinkBounds
from daror_runtime.control.safe_stop import SafeStop
from daror_runtime.control.soft_walls import SoftWalls
from daror_runtime.errors import InputError
from daror_runtime.fsm.modes import MODES
from daror_runtime.fsm.signals import SessionSignals
from daror_runtime.fsm.spec import FsmSpec, StateSpec, check_spec, load_fsm_spec
from daror_runtime.fsm.supervisor import FsmSupervisor, Response
from daror_runtime.loop import ControlLoop
from daror_runtime.models.base import CompensationModel
from daror_runtime.models.linear import APModel
from daror_runtime.online.drift import DriftTest
from daror_runtime.safety.faults import FaultKind
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.lowering import plan_lowering
from daror_runtime.safety.monitor import SafetyMonitor
from daror_runtime.session.controllers import ModeControllers, build_mode_controllers
from daror_runtime.session.events import AnnouncementKind, Announcements
from daror_runtime.session.history import SessionHistory
from daror_runtime.session.identification import abandon_run
from daror_runtime.session.jobs import Jobs
from daror_runtime.session.online import OnlineRecord
from daror_runtime.session.rom import RomEnvelope
from daror_runtime.session.settings import SessionSettings, SessionSettingsError
from hal.interface import DriveReaction, Hal
from hal.isb import IsbLimits, Shoulder, UnreachablePoseError, monitor_isb_function
from hal.robot import FloatArray, RobotDescription

if TYPE_CHECKING:
    from daror_runtime.session.compare import CompareRun

log = structlog.get_logger(__name__)


class RequestRefusedError(InputError):
    """A request the runtime refuses before queueing it (wrong state, missing data); the message says why."""


@dataclass
class Progress:
    """What the operator sees of background work (written by jobs and request handlers)."""

    last_error: str | None = None
    last_identification: dict[str, Any] | None = None
    last_model: dict[str, Any] | None = None
    last_model_refused: dict[str, Any] | None = None


class SessionCore:
    """One session's parts on one HAL: FSM, safety monitor, controllers, loop, jobs, announcements.

    Args:
        hal: the backend (not opened yet).
        session_dir: where the session's data, models and summary go.
        spec: the FSM spec (default: ``fsm_spec.yaml``, loaded and checked).
        settings: session settings.
        clock: default lock-step at the HAL's rate on a backend that owns its time
            (``hal.virtual_time``), real time otherwise.
        session_id: tags every log event of the session (default: a new random id).

    Raises:
        LockStepRefusedError: a virtual clock on a backend that does not own its time (hardware).
        FsmSpecError: the default spec does not load.
        ConfigurationError: the spec names a mode that has no controller.
    """

    def __init__(
        self,
        hal: Hal,
        session_dir: Path | str,
        spec: FsmSpec | None = None,
        settings: SessionSettings | None = None,
        clock: Clock | None = None,
        session_id: str | None = None,
    ) -> None:
        description: RobotDescription = hal.description
        # The spec's limits and e-stop reaction are checked against the robot this session drives.
        if spec is None:
            spec = load_fsm_spec(description=description)
        else:
            check_spec(spec, "fsm spec", description=description)
        self.spec = spec
        self.settings = settings or SessionSettings()
        self.hal = hal
        self.session_dir = Path(session_dir)
        self.session_id = session_id or uuid.uuid4().hex[:12]
        self.dt_s = 1.0 / hal.rate_hz
        self.clock = clock if clock is not None else clock_for(hal, self.dt_s)
        check_clock(self.clock, hal)  # lock-step only on a backend that owns its time
        self.lock_step = self.clock.virtual
        self.description = description
        self.shoulder = Shoulder.from_description(description)
        rest = self.settings.rest
        try:
            #: the rest pose of the settings in joint angles (4,) rad: where every lowering ends
            self.rest_q_rad = self.shoulder.q_from_isb(rest.pose_isb_rad)
        except UnreachablePoseError as exc:
            raise SessionSettingsError(f"session settings, field rest.pose_isb_deg: {exc}") from None
        for readonly in (True, False):  # loaded now, not in the tick that first records or checks ISB angles
            q = np.zeros(4)
            q.flags.writeable = not readonly
            self.shoulder.isb_single(q)
        self.a_priori = APModel.from_description(description, self.settings.dummy_arm, self.settings.dummy_arm)
        #: walls a few degrees inside the device's joint limits and, where the state enforces them, the pilot's
        #: ISB limits: the pilot-driven torque modes add them to their reference (docs/control.md)
        self.walls = SoftWalls(description, self.shoulder)
        self.modes: ModeControllers = build_mode_controllers(
            description,
            feedforward=self.a_priori,
            compensation_model=None,  # none until one is approved for this pilot
            dt_s=self.dt_s,
            support_level=self.settings.support_level,
            support_ramp_per_s=self.settings.support_ramp_per_s,
            handover_tolerance_nm=self.settings.handover_tolerance_nm,
            walls=self.walls,
        )
        stop = self.settings.safe_stop
        bounds = LinkBounds.from_description(description)
        #: the online indicators of every model that compensates (issue 29), observed between ticks;
        #: a link's inertia for them: the geometric mean of the bounds (the pilot's arm is not known)
        self.online = OnlineRecord(np.sqrt(bounds.inertia_min_kgm2 * bounds.inertia_max_kgm2))
        self.drift: DriftTest | None = None  # the drift test under way or the last one (issue 29, part 2)
        #: the operator confirmed the A Priori model for this pilot in this session (rom_limits' checklist)
        self.a_priori_confirmed = False
        self.compare: CompareRun | None = None  # the blind comparison under way or the last one (part 3)
        self.safe_stop = SafeStop(
            description,
            bounds,
            self.dt_s,
            self.a_priori,
            hold_s=stop.hold_s,
            handoff_s=stop.handoff_s,
            handoff_motion_rad=float(np.deg2rad(stop.handoff_motion_deg)),
        )
        self._warm_up_the_safe_stop()
        device = SafetyLimits.from_description(description)
        self.monitor = SafetyMonitor(device.for_state(0.0, float(device.max_velocity_rad_s.max())))

        def isb_function(limits: IsbLimits) -> Callable[[FloatArray], FloatArray]:
            return monitor_isb_function(self.shoulder, limits)

        isb_margin_rad = float(np.deg2rad(self.settings.isb_margin_deg))
        self.signals = SessionSignals(
            at_rest_rad_s=self.settings.at_rest_rad_s,
            isb_angles=isb_function,
            isb_margin_rad=isb_margin_rad,
            pilot=self.settings.pilot,
            drives_hardware=hal.drives_hardware,
        )
        self.supervisor = FsmSupervisor(
            self.spec,
            self.monitor,
            device,
            self.modes.by_mode(),
            self.signals,
            isb_function=isb_function,
            isb_margin_rad=isb_margin_rad,
            on_fault_acknowledged=hal.request_fault_reset,
            safe_stop=self.safe_stop,
            estop_wiring=description.estop.wiring,
            support_model=self.support_model,
        )
        self.supervisor.limits_listeners.append(self.walls.set_limits)
        self.walls.set_limits(None)  # the first state enforces no ISB limits (the spec's invariant)
        master_lost = self.spec.drive_reactions.master_lost
        hal.set_drive_reaction(DriveReaction(master_lost.ramp_s if master_lost.reaction == "ramp" else None))
        self.loop = ControlLoop(hal, self.monitor, self.supervisor, self.clock)
        self.announcements = Announcements()
        self.jobs = Jobs(threaded=not self.lock_step, on_failure=self.job_failed)
        self.progress = Progress()
        self.rom: RomEnvelope | None = None  # the range of motion being recorded
        self.collecting = False  # a finished identification run's data are being saved
        self.faults_announced = 0  # fault occurrences announced so far
        self.lowering_planned_for: float | None = None  # the reaction (its start time) a lowering was planned for
        self.announced_reaction: tuple[object, object, str] | None = None  # (plan, phase, note) last announced
        self.history = SessionHistory()  # for the lab's records (session.json)
        self.summary_due = False  # a transition happened: session.json is written again (a job), so a crash leaves it
        self.history.reached(self.supervisor.state_name)
        self.supervisor.listeners.append(self.state_changed)

    def support_model(self, state: StateSpec) -> CompensationModel | None:
        """The model whose gravity support a reaction in ``state`` uses: compensation's where the state applies it."""
        return self.modes.compensation.model if MODES[state.mode].applies_model else None

    def _warm_up_the_safe_stop(self) -> None:
        """Plan one lowering now: its compiled integrator loads here, not in the first reaction's job."""
        q = self.rest_q_rad.copy()
        q[3] += 0.05
        plan_lowering(q, self.rest_q_rad, self.shoulder)

    def service_reaction(self) -> None:
        """Between ticks: plan a lowering the safe stop waits for (a job), and announce the reaction's news."""
        supervisor = self.supervisor
        plan = supervisor.reaction
        stop = self.safe_stop
        if plan is None:
            self.announced_reaction = None
            return
        if (
            supervisor.reaction_running
            and stop.wants_path
            and self.lowering_planned_for != supervisor.reaction_started_s
        ):
            self._plan_the_lowering()
        phase = stop.phase if supervisor.reaction_running or stop.finished else None
        seen = (plan, phase, stop.note)
        if seen != self.announced_reaction:
            previous = self.announced_reaction
            self.announced_reaction = seen
            new = previous is None or previous[0] != plan
            t_s = supervisor.reaction_started_s if new and previous is None else self.t_s()
            self.announcements.announce(AnnouncementKind.REACTION, self._reaction_text(plan, previous), t_s)

    def _reaction_text(self, plan: Any, previous: tuple[object, object, str] | None) -> str:
        stop = self.safe_stop
        support = self.settings.rest.support
        if previous is None or previous[0] != plan:
            what = {
                "off": "torque off (category 0)",
                "lower": f"hold, then lower the arm to its rest on the {support} (category 1)",
                "hold": "hold the arm until the operator acts (category 2)",
            }[plan.reaction]
            off = f"; joint(s) {', '.join(map(str, plan.joints_off))} off" if plan.joints_off and plan.holds else ""
            return f"{', '.join(plan.causes)}: {what}{off}"
        if not self.supervisor.reaction_running and stop.finished:
            return f"ended: {stop.note}"
        return f"now {stop.phase.value}" + (f": {stop.note}" if stop.note else "")

    def _plan_the_lowering(self) -> None:
        """A job plans the lowering from where the safe stop holds the arm; a request hands it over at a tick boundary."""
        supervisor = self.supervisor
        token = supervisor.reaction_started_s
        self.lowering_planned_for = token
        plan = supervisor.reaction
        stop = self.safe_stop
        q_start = stop.hold_pose_rad
        joints_off = plan.joints_off if plan is not None else ()
        limits = self.signals.isb_limits
        margin = float(np.deg2rad(self.settings.isb_margin_deg))
        speed = self.settings.safe_stop.lowering_speed_rad_s

        def job() -> None:
            from daror_runtime.safety.lowering import LoweringError

            try:
                path, why = (
                    plan_lowering(q_start, self.rest_q_rad, self.shoulder, joints_off, limits, margin, speed),
                    "",
                )
            except LoweringError as exc:
                path, why = None, str(exc)

            def install(supervisor: FsmSupervisor) -> Response:
                if supervisor.reaction_started_s != token or not supervisor.reaction_running or not stop.wants_path:
                    return self.refuse("lowering", "the reaction changed while the lowering was planned")
                if not np.allclose(stop.hold_pose_rad, q_start, atol=1e-9):
                    self.lowering_planned_for = None  # planned from another pose: plan again
                    return self.refuse("lowering", "the arm is held elsewhere than the plan started: planned again")
                stop.install_path(path, why)
                if path is None:
                    log.error("reaction: no safe lowering", why=why, t_s=self.t_s())
                else:
                    log.warning(
                        "reaction: lowering planned", duration_s=round(path.duration_s, 2), method=path.method,
                        rest_deg=[round(float(v), 1) for v in np.degrees(path.q_end_rad)], t_s=self.t_s(),
                    )  # fmt: skip
                return Response("lowering", path is not None, supervisor.state_name, why)

            supervisor.post("lowering", install, essential=True)

        self.jobs.submit("plan the lowering", job)

    def t_s(self) -> float | None:
        """Robot time of the last sample (s), None before the first."""
        sample = self.signals.sample
        return sample.t_s if sample is not None else None

    def refuse(self, request: str, reason: str) -> Response:
        """A logged refusal of ``request`` at a tick boundary."""
        log.warning("refused", request=request, state=self.supervisor.state_name, reason=reason, t_s=self.t_s())
        return Response(request, False, self.supervisor.state_name, reason)

    def job_failed(self, name: str, exc: BaseException) -> None:
        self.announcements.announce(AnnouncementKind.JOB_FAILED, f"{name} failed: {exc}", self.t_s())

    def announce_new_faults(self) -> None:
        """Between ticks: announce the fault occurrences the monitor latched since the last call."""
        monitor = self.monitor
        new = monitor.occurrences - self.faults_announced
        if new <= 0:
            return
        self.faults_announced = monitor.occurrences
        state = self.supervisor.state
        testing = isinstance(state, StateSpec) and not state.fail_on_fault  # an e-stop test state
        for fault in list(monitor.recent)[-min(new, len(monitor.recent)) :]:
            self.announcements.announce(AnnouncementKind.FAULT, f"{fault.kind.value}: {fault.message}", fault.t_s)
            if testing and fault.kind is FaultKind.ESTOP:
                self.history.estop_tests += 1  # the test the state asks for, not a fault of the session
            else:
                self.history.fault(f"{fault.kind.value}: {fault.message}")

    def state_changed(self, state: Any, outcome: Any) -> None:
        """In the tick (a transition): announce it, stop what belonged to the state left; never blocks."""
        if state.name == self.spec.fail.name:
            text = f"{outcome.source} -> {state.name} ({outcome.event.value}): the fault's reaction commands the arm"
        else:
            text = f"{outcome.source} -> {state.name} ({outcome.event.value}): {state.description}"
        self.summary_due = True
        t_s = self.t_s()
        if t_s is None and self.monitor.recent:  # a tick whose reading failed: the time of the fault it raised
            t_s = self.monitor.recent[-1].t_s
        self.history.reached(state.name, t_s)
        self.announcements.announce(AnnouncementKind.TRANSITION, text, t_s)
        run = self.modes.identification.run
        if run is not None and state.mode != "identification":
            self.abandon_run(f"{outcome.event.value} to {state.name}")
        if self.rom is not None:
            if self.loop.recorder is self.rom:
                self.loop.recorder = None
            self.rom = None
            log.warning("range of motion recording discarded", reason=f"{outcome.event.value} to {state.name}")

    def abandon_run(self, reason: str) -> None:
        """The identification run under way (if any) ends without data: its recording is closed and kept, in a job."""
        mode = self.modes.identification
        run = mode.run
        if run is None:
            return
        mode.run = None
        if self.loop.recorder is run.recorder:
            self.loop.recorder = None
        self.jobs.submit("abandon identification", lambda: abandon_run(run, reason))
