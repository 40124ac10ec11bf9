"""The runtime: HAL + FSM + loop + models behind one door (DESIGN.md section 2).

The console (and every test of a session) talks only to :class:`Runtime`. A request returns a
:class:`~daror_runtime.fsm.supervisor.Ticket` at once; the request takes effect at the next tick
boundary, where the FSM decides. Work that may take long (building a trajectory and its
controller, closing a recording, reducing data, fitting a model) runs outside the tick: in the
caller's thread before the request is queued, or as a job (:mod:`daror_runtime.session.jobs`).

Two ways to drive the loop:

* **lock-step** (virtual time; tests, the demo, simulation): the caller runs ticks with
  :meth:`Runtime.run_ticks` / :meth:`Runtime.run_until`, and jobs run between two ticks, so a
  session is deterministic whatever the machine's speed;
* **real time** (hardware, a simulated plant at wall-clock rate): :meth:`Runtime.start_background`
  runs the loop on its own thread (with real-time scheduling when the OS grants it) and a service
  thread collects finished runs; :meth:`Runtime.wait` waits for a ticket with a timeout.

Raises on construction: :class:`~daror_runtime.fsm.spec.FsmSpecError` for a bad spec (the
runtime refuses to start), :class:`~daror_runtime.errors.ConfigurationError` for a spec whose
modes have no controller.
"""

from __future__ import annotations

import dataclasses
import gc
import json
import sys
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from daror_runtime.clocks import Clock, check_clock, clock_for
from daror_runtime.control.base import ControlError, ControlSettingError
from daror_runtime.control.position import LinkBounds
from daror_runtime.data.recorder import Recorder
from daror_runtime.errors import DarorError, InputError
from daror_runtime.fsm.guards import GUARDS
from daror_runtime.fsm.machine import OPERATOR_EVENTS, Event
from daror_runtime.fsm.signals import ESTOP_BUTTONS, Checklist, SessionSignals
from daror_runtime.fsm.spec import FsmSpec, StateSpec, load_fsm_spec
from daror_runtime.fsm.supervisor import FsmSupervisor, Response, Ticket
from daror_runtime.identification.protocol import IdentificationRun, let_the_writer_catch_up
from daror_runtime.logs import flush_logs, set_session_id
from daror_runtime.loop import ControlLoop, TickResult
from daror_runtime.models.linear import APModel
from daror_runtime.models.registry import kind_entry
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor
from daror_runtime.session.controllers import build_mode_controllers
from daror_runtime.session.events import AnnouncementKind, Announcements
from daror_runtime.session.identification import (
    abandon_run,
    finish_run,
    prepare_run,
    session_waypoints,
)
from daror_runtime.session.jobs import Jobs
from daror_runtime.session.rom import RomEnvelope
from daror_runtime.session.settings import SessionSettings
from daror_runtime.session.status import (
    EventGate,
    GuardState,
    JointReadings,
    LoopStatus,
    ModelStatus,
    RuntimeStatus,
)
from daror_runtime.session.training import (
    TrainedModel,
    read_model_candidate,
    train_model,
    validate_candidate,
)
from daror_runtime.util.atomic import write_text_atomic
from hal.errors import HalError
from hal.interface import Command, DriveState, Hal, Sample
from hal.isb import IsbLimits, Shoulder, monitor_isb_function

log = structlog.get_logger(__name__)

__all__ = ["RequestRefusedError", "Runtime"]


#: The interpreter's thread switch interval while the loop runs in real time (s): how long another
#: thread may keep the GIL once the loop thread asks for it.
REALTIME_SWITCH_INTERVAL_S = 1e-4
#: How often the service thread collects finished work and announces faults while the loop runs (s).
SERVICE_PERIOD_S = 0.02
#: Service periods between two collections of the garbage collector's young generations (1 s).
YOUNG_COLLECTION_EVERY = 50


class RequestRefusedError(InputError):
    """A request the runtime refuses before queueing it (wrong state, missing data); the message says why."""


@dataclass
class _Progress:
    """What the operator sees of background work."""

    last_error: str | None = None
    last_identification: dict[str, Any] | None = None
    last_model: dict[str, Any] | None = None
    last_model_refused: dict[str, Any] | None = None


@dataclass(frozen=True)
class TorqueOff:
    """How a session ended: torque off, confirmed (or not) from the drives' state read back."""

    reason: str
    state: str  # the FSM state the session was in
    t_s: float | None
    confirmed: bool  # no drive reported enabled after the torque-off command
    drives: tuple[str, ...]
    error: str | None = None

    def sentence(self) -> str:
        when = f" at t = {self.t_s:.3f} s" if self.t_s is not None else ""
        if self.confirmed:
            return f"torque off{when}: every drive disabled (state {self.state}; {self.reason})"
        problem = f": {self.error}" if self.error else f" (drives: {', '.join(self.drives) or 'no reading'})"
        return f"torque off commanded{when} but NOT confirmed{problem} (state {self.state}; {self.reason})"


def _isb_degrees(limits: IsbLimits) -> dict[str, tuple[float, float]]:
    names = ("elevation", "horizontal_rotation", "axial_rotation", "elbow")
    return {name: (r.lower_deg, r.upper_deg) for name, r in zip(names, limits.ranges, strict=True)}


class Runtime:
    """One session on one HAL.

    Args:
        hal: the backend (not opened yet; :meth:`open` opens it).
        session_dir: where the session's data, models and summary go (created).
        spec: the FSM spec (default: ``fsm_spec.yaml``, loaded and checked).
        settings: session settings.
        clock: default lock-step at the HAL's rate on a backend that owns its time
            (``hal.virtual_time``), real time otherwise.
        session_id: tags every log event of the session (default: a new random id).

    Raises:
        LockStepRefusedError: a virtual clock on a backend that does not own its time (hardware).
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
        self.spec = spec if spec is not None else load_fsm_spec()
        self.settings = settings or SessionSettings()
        self.hal = hal
        self.session_dir = Path(session_dir)
        self.session_id = session_id or uuid.uuid4().hex[:12]
        self.dt_s = 1.0 / hal.rate_hz
        self.clock = clock if clock is not None else clock_for(hal, self.dt_s)
        check_clock(self.clock, hal)  # lock-step only on a backend that owns its time
        self.lock_step = self.clock.virtual
        description = hal.description
        self.description = description
        self.shoulder = Shoulder.from_description(description)
        for readonly in (True, False):  # loaded now, not in the tick that first records or checks ISB angles
            q = np.zeros(4)
            q.flags.writeable = not readonly
            self.shoulder.isb_single(q)
        self.a_priori = APModel.from_description(description, self.settings.dummy_arm, self.settings.dummy_arm)
        self.bounds = LinkBounds.from_description(description)
        self.modes = build_mode_controllers(
            description,
            feedforward=self.a_priori,
            compensation_model=None,  # none until one is approved for this pilot
            dt_s=self.dt_s,
            support_level=self.settings.support_level,
            support_ramp_per_s=self.settings.support_ramp_per_s,
            handover_tolerance_nm=self.settings.handover_tolerance_nm,
        )
        device = SafetyLimits.from_description(description)
        self.monitor = SafetyMonitor(device.for_state(0.0, float(device.max_velocity_rad_s.max())))
        self.signals = SessionSignals(at_rest_rad_s=self.settings.at_rest_rad_s)
        self.supervisor = FsmSupervisor(
            self.spec,
            self.monitor,
            device,
            self.modes.by_mode(),
            self.signals,
            isb_function=lambda limits: monitor_isb_function(self.shoulder, limits),
            isb_margin_rad=float(np.deg2rad(self.settings.isb_margin_deg)),
        )
        self.supervisor.listeners.append(self._state_changed)
        self.loop = ControlLoop(hal, self.monitor, self.supervisor, self.clock)
        self.announcements = Announcements()
        self.jobs = Jobs(threaded=not self.lock_step, on_failure=self._job_failed)
        self.progress = _Progress()
        self._faults_announced = 0
        self.ended: TorqueOff | None = None
        self._rom: RomEnvelope | None = None
        self._collecting = False
        self._opened = False
        self._thread: threading.Thread | None = None
        self._service_thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._thread_error: BaseException | None = None
        self._switch_interval_s = sys.getswitchinterval()
        self._gc_was_enabled = True

    # --- lifecycle ------------------------------------------------------------------------

    def open(self) -> None:
        """Open the HAL, start the clock; the FSM is in its first state with torque off."""
        self.session_dir.mkdir(parents=True, exist_ok=True)
        set_session_id(self.session_id)
        self.hal.open()
        self.loop.start()
        self._opened = True
        log.info(
            "session started",
            hal=self.hal.kind,
            rate_hz=self.hal.rate_hz,
            clock="lock-step" if self.lock_step else "real time",
            state=self.supervisor.state_name,
            directory=str(self.session_dir),
        )

    def shutdown(self, reason: str) -> TorqueOff:
        """End the session now: stop the loop, write torque off to the drives, confirm it from a fresh sample.

        The first thing done when the operator quits or interrupts (Ctrl-C), in any state. The
        loop is stopped first (it finishes the tick under way), then the drives are commanded off
        and read back; the outcome is logged and announced, and :meth:`close` records it in
        ``session.json``. Idempotent: a second call returns the first report.
        """
        if self.ended is not None:
            return self.ended
        state = self.supervisor.state_name
        error: BaseException | None = None
        try:
            self.stop_background()
        except DarorError as exc:  # the loop thread had failed: still take the torque off below
            error = exc
        drives: tuple[str, ...] = ()
        t_s = self._t_s()
        confirmed = False
        if self._opened:
            try:
                self.hal.write(Command.torque_off())
                sample = self.hal.read()
            except HalError as exc:
                log.error("torque off could not be confirmed", reason=str(exc))
                error = error or exc
            else:
                self.signals.sample = sample
                t_s = sample.t_s
                drives = tuple(d.name.lower() for d in sample.drives)
                confirmed = DriveState.ENABLED not in sample.drives
        self.ended = TorqueOff(reason, state, t_s, confirmed, drives, None if error is None else str(error))
        log.warning(
            "session stopped: torque off",
            reason=reason,
            state=state,
            t_s=t_s,
            torque_off_confirmed=confirmed,
            drives=list(drives),
            error=self.ended.error,
        )
        self.announcements.announce(AnnouncementKind.SESSION, self.ended.sentence(), t_s)
        return self.ended

    def close(self) -> None:
        """Stop the loop (torque off), finish background work, close the HAL, write ``session.json``."""
        self.stop_background()
        run = self.modes.identification.run
        if run is not None:
            self.modes.identification.run = None
            self.loop.recorder = None
            self.jobs.submit("abandon identification", lambda: abandon_run(run, "the session was closed"))
        self.jobs.close()
        if self._opened:
            try:
                self.hal.close()
            finally:
                self._opened = False
        self._write_summary()
        log.info("session closed", state=self.supervisor.state_name, transitions=self.supervisor.transitions)
        flush_logs()
        set_session_id(None)

    def __enter__(self) -> Runtime:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- driving the loop -----------------------------------------------------------------

    def run_ticks(self, ticks: int, stop: Callable[[TickResult], bool] | None = None) -> TickResult | None:
        """Run ``ticks`` ticks in this thread (lock-step, or real time without a background thread)."""
        if self._thread is not None:
            raise RequestRefusedError("the loop runs in its background thread; use wait() instead")
        result = None
        tick = self.loop.tick
        service = self._service
        for n in range(ticks):
            result = tick()
            service(n)
            if stop is not None and stop(result):
                break
        return result

    def run_until(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Until ``done()`` (checked after every tick; polled in real time); False if ``timeout_s`` passed first.

        Lock-step: ticks run here, ``timeout_s`` is robot time. Background: wall-clock time.
        """
        if self._thread is not None:
            deadline = time.monotonic() + timeout_s
            while not done():
                if time.monotonic() > deadline:
                    return False
                time.sleep(0.005)
            return True
        for n in range(max(1, round(timeout_s / self.dt_s))):
            self.loop.tick()
            self._service(n)
            if done():
                return True
        return done()

    def pass_time(self, seconds: float) -> None:
        """Let ``seconds`` pass: ticks in lock-step (robot time), a sleep while the loop runs in the background."""
        if self._thread is not None:
            time.sleep(seconds)
        else:
            self.run_ticks(round(seconds / self.dt_s))

    @property
    def background(self) -> bool:
        """True while the loop runs on its own thread."""
        return self._thread is not None

    @property
    def busy(self) -> bool:
        """True while an identification run, its data or a job is in progress, or requests wait for a tick."""
        return (
            self.modes.identification.running
            or self.modes.identification.finished_run is not None
            or self._collecting
            or self.jobs.pending
            or self.supervisor.pending_requests
        )

    @property
    def at_rest(self) -> bool:
        """Every joint at rest (the ``robot_at_rest`` guard)."""
        return GUARDS["robot_at_rest"].read(self.signals)

    def wait(self, ticket: Ticket, timeout_s: float = 5.0) -> Response:
        """The response to ``ticket``: in lock-step, ticks run until it is resolved (at most ``timeout_s`` of robot time).

        Raises:
            DarorError: it was not resolved in time (the loop is not running).
        """
        if self._thread is None:
            self.run_until(lambda: ticket.done, timeout_s)
            response = ticket.response
        else:
            response = ticket.wait(timeout_s)
        if response is None:
            raise DarorError(f"request {ticket.request!r} was not applied within {timeout_s} s: is the loop running?")
        return response

    def start_background(self, realtime: bool = True) -> None:
        """Run the loop on its own thread (and a service thread) until :meth:`stop_background`."""
        if self._thread is not None:
            return
        self._stop.clear()
        if self.loop.stats.ticks > 0:  # a restart: a new grid, so the pause is not counted as a stall
            self.clock.start()

        def loop() -> None:
            from daror_runtime.realtime import release_realtime, request_realtime

            if realtime:
                request_realtime()
            stop = self._stop.is_set
            try:
                while not stop():
                    self.loop.run(100, stop=lambda _result: stop(), disable_gc=False)  # off for the whole run
            except BaseException as exc:
                self._thread_error = exc
                log.exception("control loop thread stopped")
            finally:
                if realtime:
                    release_realtime()

        def service() -> None:
            n = 0
            while not self._stop.wait(SERVICE_PERIOD_S):
                self._service(0)
                n += 1
                if n % YOUNG_COLLECTION_EVERY == 0:
                    gc.collect(1)  # the young generations only: well under a millisecond

        # The cyclic garbage collector runs in whichever thread allocates and holds the GIL while it
        # scans: a full collection in the console's thread is a stall of the loop. So it is off while
        # the loop runs; what exists now is frozen out of every scan; the service thread collects
        # the young generations once a second (what a session allocates is mostly freed by
        # reference counting; cycles older than that wait for the end of the session).
        gc.freeze()
        self._gc_was_enabled = gc.isenabled()
        gc.disable()
        # Another Python thread (the console, a job) holds the GIL for up to the switch interval
        # (5 ms by default) before the loop thread gets it: a stall the watchdog faults. 0.1 ms
        # bounds that wait; the cost is more frequent switches in the other threads.
        self._switch_interval_s = sys.getswitchinterval()
        sys.setswitchinterval(REALTIME_SWITCH_INTERVAL_S)

        self._thread = threading.Thread(target=loop, name="daror-loop", daemon=True)
        self._service_thread = threading.Thread(target=service, name="daror-service", daemon=True)
        self._thread.start()
        self._service_thread.start()

    def stop_background(self) -> None:
        """Stop the loop thread (the last tick wrote torque off through the HAL's close)."""
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        if self._service_thread is not None:
            self._service_thread.join()
        self._thread = self._service_thread = None
        sys.setswitchinterval(self._switch_interval_s)
        if self._gc_was_enabled:
            gc.enable()
        gc.unfreeze()
        if self._thread_error is not None:
            error, self._thread_error = self._thread_error, None
            raise DarorError(f"the control loop thread failed: {error!r}") from error

    # --- operator requests ----------------------------------------------------------------

    def request(self, event: Event | str) -> Ticket:
        """advance, revert, reset or acknowledge (the operator's buttons)."""
        event = Event(event)
        if event == Event.FAIL:
            raise RequestRefusedError("fail is not an operator request: faults and e-stops fail the robot")
        return self.supervisor.post_event(event, "operator")

    def advance(self) -> Ticket:
        return self.request(Event.ADVANCE)

    def revert(self) -> Ticket:
        return self.request(Event.REVERT)

    def reset(self) -> Ticket:
        return self.request(Event.RESET)

    def acknowledge(self) -> Ticket:
        return self.request(Event.ACKNOWLEDGE)

    def confirm(self, checklist: Checklist | str) -> Ticket:
        """The operator confirms a checklist of the current state (settings, installation, safety_experience)."""
        try:
            item = Checklist(checklist)
        except ValueError:
            raise RequestRefusedError(
                f"unknown checklist {checklist!r}; expected one of {', '.join(c.value for c in Checklist)}"
            ) from None

        def apply(supervisor: FsmSupervisor) -> Response:
            state = supervisor.state
            needed = isinstance(state, StateSpec) and any(
                GUARDS[g].checklist == item for g in (*state.guards.advance, *state.guards.revert) if g in GUARDS
            )
            if not needed:
                return self._refuse(f"confirm {item.value}", f"state {state.name} has no {item.value} checklist")
            if item == Checklist.A_PRIORI_MODEL:
                refusal = self._use_a_priori(supervisor)
                if refusal is not None:
                    return refusal
            supervisor.signals.confirmed.add(item)
            log.info("checklist confirmed", checklist=item.value, state=state.name, t_s=self._t_s())
            return Response(f"confirm {item.value}", True, state.name)

        log.info("request", request=f"confirm {item.value}", origin="operator", state=self.supervisor.state_name)
        return self.supervisor.post(f"confirm {item.value}", apply)

    def _use_a_priori(self, supervisor: FsmSupervisor) -> Response | None:
        """At a tick boundary: the operator approved the A Priori model; compensation uses it unless a validated model is in use."""
        selected = supervisor.signals.model
        if selected is not None and selected.validated:
            return self._refuse(
                f"confirm {Checklist.A_PRIORI_MODEL.value}",
                f"the validated model {selected.name} ({selected.kind}) is in use; the A Priori model is not needed",
            )
        self.modes.compensation.model = self.a_priori
        self.progress.last_model = self._a_priori_summary()
        log.info("model in use", **self.progress.last_model, state=supervisor.state_name, t_s=self._t_s())
        return None

    def _a_priori_summary(self) -> dict[str, Any]:
        return {
            "name": self.a_priori.name,
            "kind": self.a_priori.kind,
            "path": None,
            "validation_rmse_nm": None,
            "validation_rmse_per_joint_nm": None,
            "validated": False,
            "approved_by": "operator (A Priori model confirmed)",
            "includes_dummy_arm": self.settings.dummy_arm,
        }

    def set_support(self, level: float) -> Ticket:
        """Set the compensation support level in [0, 1] (the delivered level ramps to it)."""

        def apply(supervisor: FsmSupervisor) -> Response:
            try:
                self.modes.compensation.support_level = level
            except ControlSettingError as exc:
                return self._refuse(f"support {level}", str(exc))
            log.info("support level set", level=level, state=supervisor.state_name, t_s=self._t_s())
            return Response(f"support {level}", True, supervisor.state_name)

        log.info("request", request=f"support {level}", origin="operator", state=self.supervisor.state_name)
        return self.supervisor.post(f"support {level}", apply)

    # --- the pilot's range of motion --------------------------------------------------------

    def rom_start(self) -> Ticket:
        """Start recording the pilot's range of motion (in a state that needs the ISB limits recorded)."""
        envelope = RomEnvelope(self.shoulder, IsbLimits().horizontal_free_below_rad)

        def apply(supervisor: FsmSupervisor) -> Response:
            refusal = self._rom_state_refusal("rom start")
            if refusal is not None:
                return refusal
            if self.loop.recorder is not None:
                return self._refuse("rom start", "a recording is already running")
            self._rom = envelope
            self.loop.recorder = envelope
            log.info("range of motion recording started", state=supervisor.state_name, t_s=self._t_s())
            return Response("rom start", True, supervisor.state_name)

        log.info("request", request="rom start", origin="operator", state=self.supervisor.state_name)
        return self.supervisor.post("rom start", apply)

    def rom_stop(self) -> Ticket:
        """Stop the recording; the recorded range becomes the pilot's ISB limits (or is refused as too small)."""

        def apply(supervisor: FsmSupervisor) -> Response:
            envelope = self._rom
            if envelope is None:
                return self._refuse("rom stop", "no range of motion is being recorded")
            self._rom = None
            if self.loop.recorder is envelope:
                self.loop.recorder = None
            try:
                limits = envelope.limits(IsbLimits(), self.settings.rom_min_range_deg)
            except InputError as exc:
                return self._refuse("rom stop", str(exc))
            return self._set_isb_limits(supervisor, limits, f"recorded over {envelope.samples} ticks")

        log.info("request", request="rom stop", origin="operator", state=self.supervisor.state_name)
        return self.supervisor.post("rom stop", apply)

    def set_isb_limits(self, limits: IsbLimits, source: str = "entered") -> Ticket:
        """Use ``limits`` (e.g. from a clinical assessment file) as the pilot's ISB limits."""

        def apply(supervisor: FsmSupervisor) -> Response:
            refusal = self._rom_state_refusal("isb limits")
            return refusal if refusal is not None else self._set_isb_limits(supervisor, limits, source)

        log.info("request", request="isb limits", origin="operator", state=self.supervisor.state_name, source=source)
        return self.supervisor.post("isb limits", apply)

    def _rom_state_refusal(self, request: str) -> Response | None:
        state = self.supervisor.state
        if isinstance(state, StateSpec) and "isb_limits_recorded" in state.guards.advance:
            return None
        return self._refuse(
            request, f"the pilot's ISB limits are recorded in a state that requires them, not in {state.name}"
        )

    def _set_isb_limits(self, supervisor: FsmSupervisor, limits: IsbLimits, source: str) -> Response:
        supervisor.signals.isb_limits = limits
        supervisor.refresh_limits()
        ranges = {
            name: [round(r.lower_deg, 1), round(r.upper_deg, 1)]
            for name, r in zip(("elevation", "horizontal", "axial", "elbow"), limits.ranges, strict=True)
        }
        log.info("ISB limits recorded", source=source, limits_deg=ranges, state=supervisor.state_name, t_s=self._t_s())
        return Response("isb limits", True, supervisor.state_name, detail=limits)

    # --- identification -------------------------------------------------------------------

    def identify(self, kind: str) -> Ticket:
        """Start a training or validation run of the protocol (state with the identification mode).

        The trajectory and its controller are built here, in the caller's thread.

        Raises:
            RequestRefusedError: not in an identification state, no ISB limits, a run already going.
            TrajectoryError: the trajectory leaves the pilot's limits.
        """
        if kind not in ("training", "validation"):
            raise RequestRefusedError(f"unknown identification run {kind!r}; expected training or validation")
        state = self.supervisor.state
        if not isinstance(state, StateSpec) or state.mode != "identification":
            raise RequestRefusedError(
                f"identification runs only in a state with the identification mode, not in {state.name}"
            )
        limits = self.signals.isb_limits
        if limits is None:
            raise RequestRefusedError("the pilot's ISB limits are not recorded")
        if self.modes.identification.running or self._collecting:
            raise RequestRefusedError("an identification run is already going; stop it or wait for it")
        sample = self.signals.sample
        if sample is None:
            raise RequestRefusedError("no sample from the hardware yet")
        waypoints, outside = session_waypoints(self.settings.identification, limits, self.description)
        run = prepare_run(
            kind, self.description, sample.q_rad, waypoints, limits, self.settings.identification,
            self.a_priori, self.dt_s, self.session_dir,
        )  # fmt: skip
        # Load its compiled kernels here, not in the tick that starts the run (5 ms measured);
        # the start resets it again from that tick's sample.
        run.controller.reset(sample)
        run.controller.update(sample, self.dt_s)
        log.info(
            "request", request=f"identify {kind}", origin="operator", waypoints=len(waypoints), outside_limits=outside
        )

        def apply(supervisor: FsmSupervisor) -> Response:
            now = supervisor.signals.sample
            current = supervisor.state
            reason = None
            if not isinstance(current, StateSpec) or current.mode != "identification":
                reason = f"the state changed to {current.name}"
            elif self.monitor.faulted or now is None:
                reason = "a fault is latched"
            elif self.loop.recorder is not None:
                reason = "a recording is already running"
            if reason is None and now is not None:
                try:
                    self.modes.identification.start(run, now)
                except ControlError as exc:
                    reason = str(exc)
            if reason is not None:
                self.jobs.submit("abandon identification", lambda: abandon_run(run, reason))
                return self._refuse(f"identify {kind}", reason)
            self.loop.recorder = run.recorder
            log.info("identification started", kind=kind, robot_s=round(run.duration_s, 1), t_s=self._t_s())
            return Response(f"identify {kind}", True, supervisor.state_name, detail=run.duration_s)

        return self.supervisor.post(f"identify {kind}", apply)

    def stop_identification(self) -> Ticket:
        """Stop a run: the robot holds where it is; the recording is kept, no dataset is written."""

        def apply(supervisor: FsmSupervisor) -> Response:
            sample = supervisor.signals.sample
            mode = self.modes.identification
            if not mode.running or sample is None:
                return self._refuse("stop identification", "no identification run is going")
            run = mode.stop(sample)
            self.loop.recorder = None
            if run is not None:
                self.jobs.submit("abandon identification", lambda: abandon_run(run, "stopped by the operator"))
            return Response("stop identification", True, supervisor.state_name)

        log.info("request", request="stop identification", origin="operator", state=self.supervisor.state_name)
        return self.supervisor.post("stop identification", apply)

    # --- models ---------------------------------------------------------------------------

    def train(self, kind: str | None = None) -> None:
        """Train ``kind`` (default: the session's) on this session's identification data, as a job.

        Raises:
            UnknownModelKindError: ``kind`` is not a registered model kind.
            RequestRefusedError: the training or validation data are not saved yet.
        """
        kind = kind or self.settings.model_kind
        kind_entry(kind)  # an unknown kind is refused now, not when the job runs
        saved = self.signals.identification_saved
        missing = [k for k in ("training", "validation") if k not in saved]
        if missing:
            raise RequestRefusedError(
                f"no {' or '.join(missing)} data saved in this session yet: run the protocol first"
            )
        training, validation = saved["training"], saved["validation"]
        log.info(
            "request", request=f"train {kind}", origin="operator", training=str(training), validation=str(validation)
        )

        def job() -> None:
            try:
                trained = train_model(
                    kind, training, validation, self.description, self.settings.dummy_arm,
                    self.settings.max_validation_rmse_nm, self.session_dir,
                )  # fmt: skip
            except DarorError as exc:
                self.progress.last_error = f"train {kind}: {exc}"
                raise
            self._post_model(
                trained, f"train {kind}", {"training_data": str(training), "validation_data": str(validation)}
            )

        self.jobs.submit(f"train {kind}", job)

    def select_model(self, path: Path | str, validation: Path | str | None = None) -> None:
        """Use an existing model file once it is validated on held-out data (default: this session's validation run).

        The files are read and checked now (in the caller's thread); the validation runs as a job,
        and the model reaches compensation only if it passes.

        Raises:
            RequestRefusedError: no validation data named and none recorded in this session.
            ModelFileError, DataError, NotHeldOutError: a file that cannot be used (named in the message).
        """
        validation_path = (
            Path(validation) if validation is not None else self.signals.identification_saved.get("validation")
        )
        if validation_path is None:
            raise RequestRefusedError(
                "a model is validated on held-out data of this pilot: name a validation file or run the validation "
                "protocol first"
            )
        candidate = read_model_candidate(Path(path), validation_path, self.description)
        log.info("request", request="select model", origin="operator", model=str(path), validation=str(validation_path))

        def job() -> None:
            trained = validate_candidate(candidate, self.settings.max_validation_rmse_nm)
            self._post_model(trained, "select model")

        self.jobs.submit("select model", job)

    def _post_model(self, trained: TrainedModel, request: str, data: dict[str, str] | None = None) -> None:
        """From a job: hand a validated model to compensation at a tick boundary; refuse one that failed.

        Never while a compensation state delivers support (a model swap there is a torque step).
        """
        selected = trained.selected
        summary = {
            "name": selected.name,
            "kind": selected.kind,
            "path": str(selected.path),
            "validation_rmse_nm": trained.validation.rmse_nm,
            "validation_rmse_per_joint_nm": list(trained.validation.rmse_per_joint_nm),
            "validated": selected.validated,
            "max_validation_rmse_nm": selected.max_rmse_nm,
            **(data or {}),
        }

        def apply(supervisor: FsmSupervisor) -> Response:
            if not selected.validated:
                self.progress.last_model_refused = summary
                in_use = self.progress.last_model
                reason = (
                    f"{selected.name} failed validation: RMSE {trained.validation.rmse_nm:.3g} Nm on held-out data, "
                    f"above the session's limit of {selected.max_rmse_nm:g} Nm; it never drives the arm "
                    f"(in use: {in_use['name'] if in_use else 'no model'})"
                )
                self.announcements.announce(AnnouncementKind.MODEL, f"{request}: refused: {reason}", self._t_s())
                return self._refuse(request, reason)
            if supervisor.state.mode == "compensation":
                reason = f"{supervisor.state.name} delivers compensation: change models from another state"
                self.announcements.announce(AnnouncementKind.MODEL, f"{request}: refused: {reason}", self._t_s())
                return self._refuse(request, reason)
            self.modes.compensation.model = trained.model
            self.announcements.announce(
                AnnouncementKind.MODEL,
                f"{request} done: {selected.name} ({selected.kind}) validated, RMSE {trained.validation.rmse_nm:.3g} Nm "
                f"<= {selected.max_rmse_nm:g} Nm on held-out data; it is the compensation model now",
                self._t_s(),
            )
            supervisor.signals.model = selected
            self.progress.last_model = {**summary, "approved_by": "validation on held-out data"}
            log.info("model in use", **self.progress.last_model, state=supervisor.state_name, t_s=self._t_s())
            return Response(request, True, supervisor.state_name, detail=selected)

        self.supervisor.post(request, apply, essential=True)

    # --- what the operator sees -----------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """:meth:`snapshot` as a JSON-ready dictionary (``session.json``)."""
        return self.snapshot().as_dict()

    def snapshot(self) -> RuntimeStatus:
        """What the operator sees, read from any thread (values may be one tick old).

        Collections the tick changes are copied first in one C-level call (atomic under the GIL),
        so a snapshot never iterates one the loop is changing.
        """
        supervisor = self.supervisor
        state = supervisor.state
        signals = self.signals
        sample = signals.sample
        machine = supervisor.machine
        gates = {}
        for event in OPERATOR_EVENTS:
            transition = machine.table.get((state.name, event))
            if transition is None:
                gates[event.value] = EventGate(event.value, False, why_not=machine.why_not(event))
                continue
            guards = tuple(
                GuardState(g, GUARDS[g].description, bool(GUARDS[g].read(signals))) for g in transition.guards
            )
            gates[event.value] = EventGate(event.value, True, guards)
        run = self.modes.identification.run
        compensation = self.modes.compensation
        stats = self.loop.stats
        return RuntimeStatus(
            session_id=self.session_id,
            t_s=sample.t_s if sample is not None else None,
            state=state.name,
            number=state.number if isinstance(state, StateSpec) else None,
            superstate=state.superstate if isinstance(state, StateSpec) else None,
            mode=state.mode,
            description=state.description,
            estop_test_state=isinstance(state, StateSpec) and not state.fail_on_fault,
            gates=gates,
            faults=[f.as_dict() for f in self.monitor.latched],
            estop_pressed={
                b.value: bool(sample is not None and len(sample.estop) > i and sample.estop[i])
                for i, b in enumerate(ESTOP_BUTTONS)
            },
            estop_tested=sorted(b.value for b in set(signals.estop_tested)),  # copied at C level: the tick may add
            confirmed=sorted(c.value for c in set(signals.confirmed)),
            joints=None if sample is None else self._joint_readings(sample),
            model=self._model_status(),
            model_refused=self.progress.last_model_refused,
            support_level=compensation.support_level,
            delivered_support_level=compensation.delivered_support_level,
            handover_nm=tuple(float(v) for v in compensation.handover.remaining_nm)
            if compensation.handover.active
            else (0.0,) * 4,
            isb_limits_deg=None if signals.isb_limits is None else _isb_degrees(signals.isb_limits),
            rom_recording=self._rom is not None,
            identification_running=None
            if run is None or sample is None
            else {"kind": run.kind, "elapsed_s": sample.t_s - run.t0_s, "duration_s": run.duration_s},
            identification_saved={k: str(v) for k, v in dict(signals.identification_saved).items()},
            last_identification=self.progress.last_identification,
            jobs_pending=self.jobs.pending,
            last_error=self.progress.last_error,
            loop=LoopStatus(
                clock="lock-step" if self.lock_step else "real time",
                rate_hz=self.hal.rate_hz,
                ticks=stats.ticks,
                overruns=stats.overruns,
                missed_deadlines=stats.missed_deadlines,
                worst_lateness_ms=stats.worst_lateness_s * 1e3,
                tick_work_mean_us=stats.mean_work_s * 1e6,
                tick_work_max_us=stats.worst_work_s * 1e6,
                dropped_rows=self.loop.dropped_rows,
            ),
            transitions=supervisor.transitions,
            a_priori_includes_dummy_arm=self.settings.dummy_arm,
        )

    def _joint_readings(self, sample: Sample) -> JointReadings:
        return JointReadings(
            q_deg=tuple(float(np.degrees(v)) for v in sample.q_rad),
            dq_deg_s=tuple(float(np.degrees(v)) for v in sample.dq_rad_s),
            spring_torque_nm=tuple(float(v) for v in sample.tau_nm),
            motor_command_nm=tuple(float(v) for v in self.loop.last_command.motor_torque_nm),
            drives=tuple(d.name.lower() for d in sample.drives),
        )

    def _model_status(self) -> ModelStatus | None:
        summary = self.progress.last_model
        if summary is None or self.modes.compensation.model is None:
            return None
        per_joint = summary.get("validation_rmse_per_joint_nm")
        return ModelStatus(
            name=summary["name"],
            kind=summary["kind"],
            path=summary.get("path"),
            validated=bool(summary["validated"]),
            approved_by=summary.get("approved_by", ""),
            validation_rmse_nm=summary.get("validation_rmse_nm"),
            validation_rmse_per_joint_nm=None if per_joint is None else tuple(per_joint),
            max_validation_rmse_nm=summary.get("max_validation_rmse_nm"),
            includes_dummy_arm=summary.get("includes_dummy_arm"),
        )

    # --- internals ------------------------------------------------------------------------

    def _t_s(self) -> float | None:
        sample = self.signals.sample
        return sample.t_s if sample is not None else None

    def _refuse(self, request: str, reason: str) -> Response:
        log.warning("refused", request=request, state=self.supervisor.state_name, reason=reason, t_s=self._t_s())
        return Response(request, False, self.supervisor.state_name, reason)

    def _job_failed(self, name: str, exc: BaseException) -> None:
        self.announcements.announce(AnnouncementKind.JOB_FAILED, f"{name} failed: {exc}", self._t_s())

    def _announce_faults(self) -> None:
        """Between ticks: announce the fault occurrences the monitor latched since the last call."""
        monitor = self.monitor
        new = monitor.occurrences - self._faults_announced
        if new <= 0:
            return
        self._faults_announced = monitor.occurrences
        for fault in list(monitor.recent)[-min(new, len(monitor.recent)) :]:
            self.announcements.announce(AnnouncementKind.FAULT, f"{fault.kind.value}: {fault.message}", fault.t_s)

    def _state_changed(self, state: Any, outcome: Any) -> None:
        """In the tick (a transition): stop what belonged to the state left; never blocks."""
        if state.name == self.spec.fail.name:
            text = f"{outcome.source} -> {state.name}: torque off ({outcome.event.value})"
        else:
            text = f"{outcome.source} -> {state.name} ({outcome.event.value}): {state.description}"
        self.announcements.announce(AnnouncementKind.TRANSITION, text, self._t_s())
        mode = self.modes.identification
        run = mode.run
        if run is not None and state.mode != "identification":
            mode.run = None
            if self.loop.recorder is run.recorder:
                self.loop.recorder = None
            reason = f"{outcome.event.value} to {state.name}"
            self.jobs.submit("abandon identification", lambda: abandon_run(run, reason))
        if self._rom is not None:
            if self.loop.recorder is self._rom:
                self.loop.recorder = None
            self._rom = None
            log.warning("range of motion recording discarded", reason=f"{outcome.event.value} to {state.name}")

    def _service(self, n: int) -> None:
        """Between ticks: announce faults, collect a finished run, let a lock-step writer catch up, run lock-step jobs."""
        if self.monitor.occurrences != self._faults_announced:
            self._announce_faults()
        mode = self.modes.identification
        finished = mode.finished_run
        if finished is not None and not self._collecting:
            mode.finished_run = None
            self._collecting = True
            self.supervisor.post("identification finished", lambda supervisor: self._collect(finished), essential=True)
        if self.lock_step:
            recorder = self.loop.recorder
            if n % 500 == 0 and isinstance(recorder, Recorder):
                let_the_writer_catch_up(recorder)
            if self.jobs.pending:
                self.jobs.run_pending()

    def _collect(self, run: IdentificationRun) -> Response:
        """At a tick boundary: detach the run's recorder and reduce its data in a job."""
        if self.loop.recorder is run.recorder:
            self.loop.recorder = None
        log.info("identification trajectory finished", kind=run.kind, t_s=self._t_s())

        def job() -> None:
            try:
                data = finish_run(run)
            except DarorError as exc:
                self.progress.last_error = f"identification {run.kind}: {exc}"
                log.error("identification data not saved", kind=run.kind, reason=str(exc))
                raise
            finally:
                self._collecting = False
            self.progress.last_identification = {
                "kind": data.kind,
                "dataset": str(data.dataset_path),
                "points": data.points,
                "tracking_rms_mrad": [float(v * 1e3) for v in data.tracking_rms_rad],
                "tracking_max_mrad": [float(v * 1e3) for v in data.tracking_max_rad],
            }

            def saved(supervisor: FsmSupervisor) -> Response:
                supervisor.signals.identification_saved[data.kind] = data.dataset_path
                self.announcements.announce(
                    AnnouncementKind.IDENTIFICATION,
                    f"identification {data.kind} done: {data.points} stationary points saved to {data.dataset_path}",
                    self._t_s(),
                )
                return Response("identification saved", True, supervisor.state_name, detail=data)

            self.supervisor.post("identification saved", saved, essential=True)

        self.jobs.submit(f"save identification {run.kind}", job)
        return Response("identification finished", True, self.supervisor.state_name)

    def _write_summary(self) -> None:
        if not self.session_dir.exists():
            return
        document = self.status()
        document["failures"] = [f"{name}: {exc}" for name, exc in self.jobs.failures]
        document["ended"] = None if self.ended is None else dataclasses.asdict(self.ended)
        write_text_atomic(self.session_dir / "session.json", json.dumps(document, indent=2, default=str) + "\n")
