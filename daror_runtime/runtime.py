"""The runtime: one session on one HAL behind one narrow door.

The console, the demo and every tool talk only to :class:`Runtime`: the operator's requests, a
typed status (:meth:`Runtime.snapshot`), the announcements, and the loop's lifecycle. What the
session is made of (FSM supervisor, safety monitor, controllers, loop, jobs) is private:
:mod:`daror_runtime.session.core` wires it, :mod:`daror_runtime.session.requests` applies the
requests to it, :mod:`daror_runtime.session.snapshot` reads it.

A request returns a :class:`~daror_runtime.fsm.supervisor.Ticket` at once; it takes effect at the
next tick boundary, where the FSM decides. Work that may take long (building a trajectory and its
controller, closing a recording, reducing data, fitting a model) runs outside the tick: in the
caller's thread before the request is queued, or as a job (:mod:`daror_runtime.session.jobs`).

Driving the loop is the :class:`~daror_runtime.runner.LoopRunner`'s job (:attr:`Runtime.runner`):
lock-step ticks in the caller's thread (a backend that owns its time: the simulated plant; tests,
the demo; refused on hardware), or the loop on its own thread with the interpreter's settings that
keep other threads from stalling it (hardware, or a simulated plant at wall-clock rate on a
:class:`~daror_runtime.clocks.PacedClock`). The runtime itself owns no thread.

Raises on construction: :class:`~daror_runtime.fsm.spec.FsmSpecError` for a bad spec (the
runtime refuses to start), :class:`~daror_runtime.errors.ConfigurationError` for a spec whose
modes have no controller, :class:`~daror_runtime.clocks.LockStepRefusedError` for lock-step on
hardware.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import structlog

from daror_runtime.clocks import Clock
from daror_runtime.errors import DarorError
from daror_runtime.fsm.guards import GUARDS
from daror_runtime.fsm.machine import Event, Outcome
from daror_runtime.fsm.signals import Checklist, SelectedModel
from daror_runtime.fsm.spec import FsmSpec, StateSpec
from daror_runtime.fsm.supervisor import Response, Ticket
from daror_runtime.logs import flush_logs, set_session_id, set_session_pilot
from daror_runtime.runner import LoopRunner
from daror_runtime.session import requests
from daror_runtime.session.compare import request_compare, request_rating, service_compare
from daror_runtime.session.core import RequestRefusedError, SessionCore
from daror_runtime.session.drift import request_drift_test, service_drift
from daror_runtime.session.events import Announcement, AnnouncementKind
from daror_runtime.session.history import utc_now
from daror_runtime.session.online import observe_online
from daror_runtime.session.provenance import session_pilot, session_robot
from daror_runtime.session.settings import SessionSettings
from daror_runtime.session.snapshot import snapshot
from daror_runtime.session.status import RuntimeStatus
from daror_runtime.util.atomic import write_text_atomic
from hal.capabilities import SimulatedWorld
from hal.errors import HalError
from hal.interface import Command, DriveState, Hal, Sample
from hal.isb import IsbLimits, Shoulder
from hal.robot import FloatArray, RobotDescription

log = structlog.get_logger(__name__)

__all__ = ["RequestRefusedError", "Runtime", "TorqueOff"]


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
        operator: str | None = None,
    ) -> None:
        self._core = SessionCore(hal, session_dir, spec, settings, clock, session_id)
        self._operator = operator
        self.ended: TorqueOff | None = None
        self.ended_utc: str | None = None  # the wall-clock time the session ended (UTC)
        self._opened = False
        self._runner = LoopRunner(self._core.loop, self._core.clock, self._service, self._display_failed)

    # --- what the session is (read-only) ------------------------------------------------------

    @property
    def session_id(self) -> str:
        return self._core.session_id

    @property
    def operator(self) -> str | None:
        """Who runs the session, as the lab's records keep it (``daror console --operator``; None: unknown)."""
        return self._operator

    @property
    def session_dir(self) -> Path:
        return self._core.session_dir

    @property
    def settings(self) -> SessionSettings:
        return self._core.settings

    @property
    def spec(self) -> FsmSpec:
        return self._core.spec

    @property
    def description(self) -> RobotDescription:
        """The robot this session drives (the backend's description)."""
        return self._core.description

    @property
    def shoulder(self) -> Shoulder:
        """The shoulder's kinematics of this robot (ISB angles and joint angles, both ways)."""
        return self._core.shoulder

    @property
    def rate_hz(self) -> float:
        """The loop's rate (the backend's)."""
        return self._core.hal.rate_hz

    @property
    def lock_step(self) -> bool:
        """True when the session runs on virtual time (the caller runs the ticks)."""
        return self._core.lock_step

    @property
    def world(self) -> SimulatedWorld | None:
        """The simulated world around the robot (pilot, e-stop buttons, faults), or None on hardware."""
        return self._core.hal.world

    @property
    def state_name(self) -> str:
        """The FSM's current state."""
        return self._core.supervisor.state_name

    @property
    def last_sample(self) -> Sample | None:
        """The last sample the loop read (an immutable record), None before the first tick."""
        return self._core.signals.sample

    @property
    def model_in_use(self) -> SelectedModel | None:
        """The model validated for this pilot and handed to compensation, None before one is."""
        return self._core.signals.model

    @property
    def torque_reference_nm(self) -> FloatArray | None:
        """The spring torques (Nm) compensation asked for in the last tick: support x the model's torque (with the
        entry's handover); None outside compensation. A new array every tick: safe to read from any thread."""
        core = self._core
        if core.supervisor.state.mode != "compensation":
            return None
        return core.modes.compensation.last_reference_nm

    def drain_announcements(self) -> list[Announcement]:
        """What happened since the last call (transitions, faults, finished work), oldest first."""
        return self._core.announcements.drain()

    def on_transition(self, listener: Callable[[StateSpec, Outcome], None]) -> None:
        """Call ``listener(state, outcome)`` in the tick after every transition (it must not block)."""
        self._core.supervisor.listeners.append(listener)

    # --- lifecycle ------------------------------------------------------------------------

    def open(self) -> None:
        """Open the HAL, start the clock; the FSM is in its first state with torque off."""
        core = self._core
        core.session_dir.mkdir(parents=True, exist_ok=True)
        set_session_id(core.session_id)
        set_session_pilot(session_pilot(core))
        core.hal.open()
        core.loop.start()
        self._opened = True
        self._write_summary(durable=False)  # from the start: a session killed before its first transition has one
        log.info(
            "session started",
            hal=core.hal.kind,
            rate_hz=core.hal.rate_hz,
            clock=core.clock.name,
            state=core.supervisor.state_name,
            directory=str(core.session_dir),
            operator=self._operator,
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
        core = self._core
        state = core.supervisor.state_name
        error: BaseException | None = None
        try:
            self._runner.stop()
        except DarorError as exc:  # the loop thread had failed: still take the torque off below
            error = exc
        drives: tuple[str, ...] = ()
        t_s = core.t_s()
        confirmed = False
        if self._opened:
            try:
                core.hal.write(Command.torque_off())
                sample = core.hal.read()
            except HalError as exc:
                log.error("torque off could not be confirmed", reason=str(exc))
                error = error or exc
            else:
                core.signals.sample = sample
                t_s = sample.t_s
                drives = tuple(d.name.lower() for d in sample.drives)
                confirmed = DriveState.ENABLED not in sample.drives
        self.ended = TorqueOff(reason, state, t_s, confirmed, drives, None if error is None else str(error))
        self.ended_utc = utc_now()
        log.warning(
            "session stopped: torque off",
            reason=reason,
            state=state,
            t_s=t_s,
            torque_off_confirmed=confirmed,
            drives=list(drives),
            error=self.ended.error,
        )
        core.announcements.announce(AnnouncementKind.SESSION, self.ended.sentence(), t_s)
        return self.ended

    def close(self) -> None:
        """Stop the loop (torque off), finish background work, close the HAL, write ``session.json``."""
        core = self._core
        self._runner.stop()
        core.abandon_run("the session was closed")
        core.jobs.close()
        if self._opened:
            try:
                core.hal.close()
            finally:
                self._opened = False
        self._write_summary()
        log.info("session closed", state=core.supervisor.state_name, transitions=core.supervisor.transitions)
        flush_logs()
        set_session_id(None)
        set_session_pilot(None)

    def __enter__(self) -> Runtime:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- what the loop is doing ----------------------------------------------------------------

    @property
    def runner(self) -> LoopRunner:
        """Who runs the ticks: lock-step in the caller's thread, or the loop on its own thread (:mod:`daror_runtime.runner`)."""
        return self._runner

    @property
    def busy(self) -> bool:
        """True while an identification run, its data or a job is in progress, or requests wait for a tick."""
        core = self._core
        return (
            core.modes.identification.running
            or core.modes.identification.finished_run is not None
            or core.collecting
            or core.jobs.pending
            or core.supervisor.pending_requests
        )

    @property
    def jobs_pending(self) -> int:
        """Background jobs (saving data, fitting, validating) not finished yet."""
        return self._core.jobs.pending

    @property
    def arm_held(self) -> bool:
        """True while a fault's reaction holds or lowers the pilot's arm (the ``arm_released`` guard does not hold)."""
        return self._core.signals.arm_held

    @property
    def at_rest(self) -> bool:
        """Every joint at rest (the ``robot_at_rest`` guard)."""
        return GUARDS["robot_at_rest"].read(self._core.signals)

    def wait(self, ticket: Ticket, timeout_s: float = 5.0) -> Response:
        """The response to ``ticket``: in lock-step, ticks run until it is resolved (at most ``timeout_s`` of robot time).

        Raises:
            DarorError: it was not resolved in time (the loop is not running).
        """
        response = self._runner.wait_for(ticket, timeout_s)
        if response is None:
            raise DarorError(f"request {ticket.request!r} was not applied within {timeout_s} s: is the loop running?")
        return response

    # --- operator requests (docs/session.md; applied at the next tick boundary) ----------------

    def request(self, event: Event | str) -> Ticket:
        """advance, revert, reset or acknowledge (the operator's buttons)."""
        return requests.request_event(self._core, event)

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
        return requests.confirm(self._core, checklist)

    def name_pilot(self, code: str) -> Ticket:
        """Name the session's pilot by his code (:func:`daror_runtime.session.requests.name_pilot`)."""
        return requests.name_pilot(self._core, code)

    def set_support(self, level: float) -> Ticket:
        """Set the compensation support level in [0, 1] (the delivered level ramps to it)."""
        return requests.set_support(self._core, level)

    def drift_test(self) -> Ticket:
        """Start a drift test (issue 29, docs/online.md): the model alone holds the relaxed arm, the
        session catches it after at most 1 s or 3 deg and measures the torque the model missed there.
        Refused (with the reason) outside state compensation, below support level 1, with the arm
        moving or near a limit."""
        return request_drift_test(self._core)

    def compare(self, pairs: int = 8, block_s: float = 20.0, seed: int | None = None) -> Ticket:
        """Start a blind comparison of the validated model in use with the confirmed A Priori model
        (issue 29, docs/online.md): ``pairs`` pairs of blocks of ``block_s`` s, in a balanced random
        order (``seed``; None: drawn) the console does not show, each rated by the pilot (:meth:`rate`)."""
        return request_compare(self._core, pairs, block_s, seed)

    def rate(self, rating: float | None) -> Ticket:
        """The pilot's rating (0-10) of the comparison's block just ended; None: the simulated pilot rates."""
        return request_rating(self._core, rating)

    def rom_start(self) -> Ticket:
        """Start recording the pilot's range of motion (in a state that needs the ISB limits recorded)."""
        return requests.rom_start(self._core)

    def rom_stop(self) -> Ticket:
        """Stop the recording; the recorded range becomes the pilot's ISB limits (or is refused as too small)."""
        return requests.rom_stop(self._core)

    def set_isb_limits(self, limits: IsbLimits, source: str = "entered") -> Ticket:
        """Use ``limits`` (e.g. from a clinical assessment file) as the pilot's ISB limits."""
        return requests.set_isb_limits(self._core, limits, source)

    def lower_arm(self) -> Ticket:
        """A fault's reaction holds the arm: lower it to the rest pose of the settings (docs/safety.md)."""
        return requests.lower_arm(self._core)

    def release_arm(self) -> Ticket:
        """A fault's reaction holds the arm and someone holds it too: ramp the torque to zero."""
        return requests.release_arm(self._core)

    def identify(self, kind: str) -> Ticket:
        """Start a training or validation run of the protocol (:func:`daror_runtime.session.requests.identify`)."""
        return requests.identify(self._core, kind)

    def stop_identification(self) -> Ticket:
        """Stop a run: the robot holds where it is; the recording is kept, no dataset is written."""
        return requests.stop_identification(self._core)

    def train(self, kind: str | None = None) -> Ticket:
        """Train ``kind`` (default: the session's) on this session's data, as a job (:func:`daror_runtime.session.requests.train`).

        The ticket is resolved when the model is handed over or refused at a tick boundary, or
        refused when the job fails.
        """
        return requests.train(self._core, kind)

    def select_model(
        self, path: Path | str, validation: Path | str | None = None, accept_nonconservative: bool = False
    ) -> Ticket:
        """Use a model file once validated on held-out data of this pilot (:func:`daror_runtime.session.requests.select_model`).

        ``accept_nonconservative``: the operator confirms a model the closed-path test finds not
        conservative, after he saw its energy figure.
        """
        return requests.select_model(self._core, path, validation, accept_nonconservative)

    # --- what the operator sees -----------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """:meth:`snapshot` as a JSON-ready dictionary (``session.json``)."""
        return self.snapshot().as_dict()

    def snapshot(self) -> RuntimeStatus:
        """What the operator sees, read from any thread (values may be one tick old)."""
        return snapshot(self._core)

    # --- internals ------------------------------------------------------------------------

    def _service(self, n: int) -> None:
        """Between ticks: announce faults, collect a finished run, let a lock-step writer catch up, run lock-step jobs."""
        core = self._core
        if core.monitor.occurrences != core.faults_announced:  # runs every tick: test before calling
            core.announce_new_faults()
        if core.supervisor.reaction is not None or core.announced_reaction is not None:
            core.service_reaction()
        if core.modes.identification.finished_run is not None:
            requests.collect_finished_run(core)
        observe_online(core)  # issue 29: the indicators, every 20 ms of robot time (a comparison first)
        if core.drift is not None:
            service_drift(core)  # issue 29: a drift test under way: the catch, the hold's measure
        if core.compare is not None:
            service_compare(core)  # issue 29: a blind comparison's blocks
        if core.summary_due:  # a transition: session.json is kept current (a crash leaves the last state)
            core.summary_due = False
            core.jobs.submit("write session.json", lambda: self._write_summary(durable=False))
        if core.lock_step:
            requests.keep_up_with_the_recorder(core, n)
            if core.jobs.pending:
                core.jobs.run_pending()

    def _display_failed(self, exc: Exception) -> None:
        """A display's publisher raised (the runner dropped it): the operator is told."""
        self._core.announcements.announce(
            AnnouncementKind.SESSION, f"a display stopped receiving data: {exc}", self._core.t_s()
        )

    def _write_summary(self, durable: bool = True) -> None:
        """``session.json`` now; ``durable`` False after a transition (no fsync: a killed process leaves it
        whole; the ending's write is durable)."""
        core = self._core
        if not core.session_dir.exists():
            return
        document = self.status()
        document["failures"] = [f"{name}: {exc}" for name, exc in core.jobs.failures]
        document["ended"] = None if self.ended is None else dataclasses.asdict(self.ended)
        # for the lab's records (daror_runtime/records): whose session, on what, when, what it did
        document["pilot"] = session_pilot(core)
        document["operator"] = self._operator
        document["robot"] = session_robot(core)
        document["backend"] = core.hal.kind
        document["simulated"] = core.hal.world is not None
        document["history"] = core.history.as_dict()
        document["ended_utc"] = None if self.ended is None else self.ended_utc
        document["updated_utc"] = utc_now()  # after a crash: the last moment the session was known alive
        write_text_atomic(
            core.session_dir / "session.json", json.dumps(document, indent=2, default=str) + "\n", durable=durable
        )
