"""The FSM inside the tick: requests, faults and e-stops in; the controller and the limits out.

Per tick (docs/loop.md), after the safety monitor checked the sample::

    on_tick(sample, faults, monitor):
        faults of this tick  -> fail (same tick), or, in an e-stop test state, recorded as the test
        released e-stop      -> unlatched again in a test state (it was a test)
        queued requests      -> applied in the order posted (operator events, confirmations, ...),
                                at most ``max_requests_per_tick`` and at most one state change
        state's controller   -> returned; the loop runs it unless a fault is latched

Rules kept here:

* Requests take effect only here, at a tick boundary; :meth:`FsmSupervisor.post` may be called
  from any thread and returns a :class:`Ticket` that is resolved in the tick that applied it.
* The queue is bounded, so a flood of requests cannot stall a tick: at most
  ``max_pending_requests`` wait (a post beyond that is refused at once, its ticket resolved with
  the reason; a burst of refusals is logged as one warning and a summary, not one line each), and
  a tick applies at most ``max_requests_per_tick`` of them and stops after the first that changed
  the state (the next request is decided in a later tick, against the new state's limits, guards
  and freshly reset controller). The rest wait, in order. Posting takes a lock only around the
  length check and the append; the tick pops without it (``deque.popleft`` is atomic).
* A fault fires ``fail`` in the tick it was found, also when the loop finds it late in the tick
  (a controller error: :meth:`FsmSupervisor.on_late_faults`). Entering a state that fails on
  faults while a fault is latched (a reset or revert out of a test state) fails at once.
* The state picks the controller (by its mode) and the limits (its torque and velocity limits
  within the device's, plus the pilot's ISB limits where the state enforces them); the filter
  after the controller enforces them, so a controller never has to know the state.
* A controller is reset with the current sample before its first update in a state, and again
  when torque returns after a latched fault, so no filter or observer resumes from stale state.
* Every fault is met, in the tick it is found, with the reaction the spec declares for its kind
  (``fault_reactions``; :mod:`daror_runtime.safety.reactions`): off, or the safe stop controller
  holding and lowering the arm (:class:`~daror_runtime.control.safe_stop.SafeStop`), with the
  joints a fault took off disabled. The supervisor grants the reaction to the monitor's filter
  (a new fault withdraws it until decided); a reaction only gets stricter until it ends: at its
  rest (the torque off), when a test state's faults are cleared, or by a reset out of FAIL
  (which needs ``arm_released``). Its start, every change and its end are in the audit log.
* Everything is in the audit log: every request, transition, refusal (with the unmet guards
  named), e-stop test and fault.

The work of a tick with no fault and no request is a handful of attribute reads (the benchmark
``bench/bench_fsm.py`` measures it).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import structlog

from daror_runtime.control.base import ControlError, Controller
from daror_runtime.control.safe_stop import SafeStop, SafeStopPhase
from daror_runtime.errors import ConfigurationError, DarorError
from daror_runtime.fsm.guards import GUARDS
from daror_runtime.fsm.machine import Event, Outcome, SafetyMachine
from daror_runtime.fsm.modes import MODES
from daror_runtime.fsm.signals import ESTOP_BUTTONS, SessionSignals
from daror_runtime.fsm.spec import FailSpec, FsmSpec, StateSpec
from daror_runtime.safety.faults import Fault, FaultKind
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import IsbFunction, SafetyMonitor
from daror_runtime.safety.reactions import ReactionPlan, escalate, plan_reaction
from hal.interface import DriveState, Sample
from hal.isb import IsbLimits
from hal.robot import N_JOINTS

if TYPE_CHECKING:
    from daror_runtime.models.base import CompensationModel

log = structlog.get_logger(__name__)

__all__ = ["DEFAULT_MAX_PENDING_REQUESTS", "DEFAULT_MAX_REQUESTS_PER_TICK", "FsmSupervisor", "Response", "Ticket"]

#: Requests that may wait for the loop. An operator presses a few buttons a second and the
#: runtime's own jobs post one request each; 64 is far above both, and small enough that the
#: queue drains in a few ticks.
DEFAULT_MAX_PENDING_REQUESTS = 64

#: Requests one tick applies at most. A refused FSM event costs ~0.1 ms of the tick with the audit
#: log on (its two log events are rendered in the tick), a transition ~0.5 ms; 4 keep a tick's
#: request work near 0.4 ms of the 1 ms period (the rest of the tick is ~0.04 ms), two are what an
#: operator's step needs (a confirmation, then the advance), and 64 waiting requests drain in 16
#: ticks (16 ms).
DEFAULT_MAX_REQUESTS_PER_TICK = 4

#: While a flood lasts, a summary of its refusals is logged every this many.
_FLOOD_LOG_EVERY = 10_000


@dataclass(frozen=True)
class Response:
    """The answer to one request: accepted or refused, and why (as logged)."""

    request: str
    accepted: bool
    state: str  # the state after the request
    reason: str = ""
    unmet: tuple[str, ...] = ()
    detail: Any = None


class Ticket:
    """A posted request; :meth:`wait` until the tick that applied it resolved it."""

    def __init__(self, request: str) -> None:
        self.request = request
        self._done = threading.Event()
        self._response: Response | None = None

    @property
    def done(self) -> bool:
        return self._done.is_set()

    @property
    def response(self) -> Response | None:
        return self._response

    def resolve(self, response: Response) -> None:
        self._response = response
        self._done.set()

    def wait(self, timeout_s: float | None = None) -> Response | None:
        """The response, or None if the loop did not apply the request within ``timeout_s``."""
        self._done.wait(timeout_s)
        return self._response


#: A request as the supervisor applies it: called at a tick boundary, returns the response.
Action = Callable[["FsmSupervisor"], Response]
IsbFunctionFactory = Callable[[IsbLimits], IsbFunction]


class FsmSupervisor:
    """The :class:`daror_runtime.loop.Supervisor` of a session.

    Args:
        spec: the checked FSM spec.
        monitor: the loop's safety monitor (the supervisor sets its limits per state).
        device_limits: the device's limits (the states narrow them).
        controllers: mode name -> controller (None: torque off); every mode the spec names.
        signals: the session signals the guards read (the supervisor keeps ``sample`` and
            ``monitor`` current and records e-stop tests in it).
        isb_function: builds the monitor's ISB-angle function for recorded limits (needed when a
            state enforces them).
        isb_margin_rad: tolerance added outside the recorded ISB limits.
        max_pending_requests: requests that may wait for the loop; a post beyond them is refused
            at once (at least 1).
        max_requests_per_tick: requests one tick applies at most (at least 1); a tick also stops
            after the first request that changed the state.
        on_fault_acknowledged: called when the operator acknowledges (the drives' fault reset).
        safe_stop: the controller of the ``hold`` and ``lower`` reactions (None: every reaction is
            off, as for a spec that declares only off).
        estop_wiring: the robot's e-stop wiring (``sto``: a press has cut the power in hardware).
        support_model: the model whose gravity support a reaction uses in a state: the compensation
            model where the state applies one, else None (the A Priori model).

    Raises:
        ConfigurationError: a mode of the spec has no controller entry; a queue bound below 1.
    """

    def __init__(
        self,
        spec: FsmSpec,
        monitor: SafetyMonitor,
        device_limits: SafetyLimits,
        controllers: Mapping[str, Controller | None],
        signals: SessionSignals | None = None,
        isb_function: IsbFunctionFactory | None = None,
        isb_margin_rad: float = 0.0,
        max_pending_requests: int = DEFAULT_MAX_PENDING_REQUESTS,
        max_requests_per_tick: int = DEFAULT_MAX_REQUESTS_PER_TICK,
        on_fault_acknowledged: Callable[[], None] | None = None,
        safe_stop: SafeStop | None = None,
        estop_wiring: str = "sto",
        support_model: Callable[[StateSpec], CompensationModel | None] | None = None,
    ) -> None:
        if max_pending_requests < 1 or max_requests_per_tick < 1:
            raise ConfigurationError(
                f"the request queue needs max_pending_requests >= 1 and max_requests_per_tick >= 1, "
                f"got {max_pending_requests} and {max_requests_per_tick}"
            )
        self._on_fault_acknowledged = on_fault_acknowledged
        modes = {s.mode for s in spec.states} | {spec.fail.mode}
        missing = sorted(modes - set(controllers))
        if missing:
            raise ConfigurationError(f"no controller for the mode(s) {', '.join(missing)} the FSM spec uses")
        for mode in modes:
            if not MODES[mode].applies_torque and controllers[mode] is not None:
                raise ConfigurationError(f"mode {mode!r} applies no torque, so its controller must be None")
        self.spec = spec
        self.monitor = monitor
        self.device_limits = device_limits
        self.controllers = dict(controllers)
        self.signals = signals if signals is not None else SessionSignals()
        self.signals.monitor = monitor
        self._isb_function = isb_function
        self.isb_margin_rad = isb_margin_rad
        self.machine = SafetyMachine(spec, GUARDS.bind(self.signals), on_acknowledge=self._acknowledged)
        self._requests: deque[tuple[Action, Ticket]] = deque()
        self.max_pending_requests = max_pending_requests
        self.max_requests_per_tick = max_requests_per_tick
        self._post_lock = threading.Lock()  # held by post (check + append) and for the flood counters only
        self._flood_refused = 0  # refusals of the current burst
        self.refused_requests = 0  # refused because too many waited, since the start
        self._controller: Controller | None = None
        self._needs_reset = False
        self._was_faulted = False
        self._fail_on_fault = True
        self._t_s = 0.0
        self._tick_faults: list[Fault] = []  # the loop's list of this tick's faults (ours go in too)
        self.transitions = 0
        self.listeners: list[Callable[[StateSpec | FailSpec, Outcome], None]] = []
        self.safe_stop = safe_stop
        self.estop_wiring = estop_wiring
        self._support_model = support_model
        #: The reaction to the latched faults (None: none since the last reset or cleared test faults).
        self.reaction: ReactionPlan | None = None
        self.reaction_started_s: float | None = None
        self._reaction_state = spec.first  # the state the reaction's first fault was found in
        self._reaction_deadline_s = float("inf")
        self._reaction_running = False  # the safe stop holds the arm (torque on under the reaction)
        self._stop_phase: SafeStopPhase | None = None
        self._drives: tuple[DriveState, ...] = (DriveState.DISABLED,) * N_JOINTS  # of the last sample
        #: Called in the tick a reaction starts or gets stricter, with the plan (the session plans a lowering).
        self.reaction_listeners: list[Callable[[ReactionPlan], None]] = []
        #: Called whenever the state's limits are applied, with the pilot's ISB limits it enforces (None:
        #: none): the soft walls of the torque modes follow them.
        self.limits_listeners: list[Callable[[IsbLimits | None], None]] = []
        self._enter(spec.first, None)

    # --- what the rest of the runtime reads -----------------------------------------------

    @property
    def state(self) -> StateSpec | FailSpec:
        return self.machine.state

    @property
    def state_name(self) -> str:
        return self.machine.state_name

    @property
    def controller(self) -> Controller | None:
        return self._controller

    @property
    def pending_requests(self) -> bool:
        """True while posted requests wait for the next tick boundary."""
        return bool(self._requests)

    @property
    def waiting_requests(self) -> int:
        """How many posted requests wait for a tick (at most ``max_pending_requests``, plus essential ones)."""
        return len(self._requests)

    # --- requests (any thread) ------------------------------------------------------------

    def post(self, request: str, action: Action, *, essential: bool = False, ticket: Ticket | None = None) -> Ticket:
        """Queue ``action`` for a tick boundary; ``request`` names it in the log. Any thread; never blocks long.

        When ``max_pending_requests`` already wait, the request is refused at once: the returned
        ticket is already resolved with ``accepted=False`` and the reason. The first refusal of a
        burst is logged as a warning, then a summary every 10,000 and one when the burst ends (the
        first tick that finds the queue empty again).

        Args:
            request: the request's name in the log and in its response.
            action: applied at a tick boundary; returns the response.
            essential: the runtime's own bookkeeping (a finished run collected, a saved dataset,
                a trained model handed over): queued even beyond the bound, since losing it would
                lose data, and there is at most one per job, not one per caller's wish.
            ticket: the ticket to resolve (one the caller handed out before the work that led to
                this request, e.g. a training job's); default a new one.
        """
        if ticket is None:
            ticket = Ticket(request)
        with self._post_lock:  # the length check and the append as one step (held for nothing else)
            if essential or len(self._requests) < self.max_pending_requests:
                self._requests.append((action, ticket))
                return ticket
            self._flood_refused = refused = self._flood_refused + 1
            self.refused_requests += 1
        limit = self.max_pending_requests
        reason = f"too many requests waiting for the loop ({limit}); this one was refused"
        ticket.resolve(Response(request, False, self.state_name, reason))
        if refused == 1:
            log.warning("requests refused: too many waiting for the loop", request=request, limit=limit)
        elif refused % _FLOOD_LOG_EVERY == 0:
            log.warning("requests still refused: too many waiting for the loop", refused=refused, limit=limit)
        return ticket

    def post_event(self, event: Event | str, origin: str = "operator") -> Ticket:
        """Queue an FSM event (advance, revert, reset, acknowledge) from ``origin`` (see :meth:`post`)."""
        event = Event(event)
        return self.post(event.value, lambda supervisor: supervisor.fire(event, origin))

    # --- the tick -------------------------------------------------------------------------

    def on_tick(self, sample: Sample | None, faults: list[Fault], monitor: SafetyMonitor) -> Controller | None:
        """The FSM's part of a tick (called by the loop after the safety check)."""
        signals = self.signals
        signals.sample = sample
        self._tick_faults = faults
        if sample is not None:
            self._t_s = sample.t_s
        if faults:
            self._route(faults, sample)
        if monitor.faulted and not self._fail_on_fault:  # a test state: an e-stop was a test, once released
            monitor.clear_kinds((FaultKind.ESTOP,))
        if self._requests:
            self._apply_requests()
        elif self._flood_refused:  # a flood ended with nothing left to apply: say how many were refused
            with self._post_lock:  # post holds it only for a length check and an append
                ended, self._flood_refused = self._flood_refused, 0
            if ended:
                self._log_flood_end(ended)
        faulted = monitor.faulted
        if self.reaction is not None:
            if not faulted and not self.machine.in_fail:
                self._end_reaction("the faults were cleared: the state's own controller takes over")
            elif self._reaction_running:
                self._follow_the_stop()
        elif self._was_faulted and not faulted:
            self._needs_reset = True  # torque comes back: start the controller from the present
        self._was_faulted = faulted
        if sample is not None:
            self._drives = sample.drives
        if self._needs_reset and sample is not None and monitor.torque_permitted:
            self._reset_controller(sample)
        return self._controller

    def on_late_faults(self, sample: Sample | None, faults: list[Fault]) -> None:
        """Faults the loop found after :meth:`on_tick` (controller, recorder, HAL write): same tick.

        The loop then asks :attr:`controller` again: a reaction that holds the arm runs in this very tick.
        """
        self._route(faults, sample)
        if self._needs_reset and sample is not None and self.monitor.torque_permitted:
            self._reset_controller(sample)

    # --- the fault's reaction ---------------------------------------------------------------

    @property
    def reaction_running(self) -> bool:
        """True while a reaction holds the arm (the safe stop controller commands torque)."""
        return self._reaction_running

    def lowering_refused(self) -> str | None:
        """Why the operator may not ask for a lowering now (None: he may)."""
        stop = self.safe_stop
        if not self._reaction_running or stop is None:
            return "no fault reaction holds the arm"
        if stop.phase not in (SafeStopPhase.HOLD, SafeStopPhase.HELD):
            return f"the arm is already being stopped ({stop.phase.value})"
        if stop.phase is SafeStopPhase.HELD and stop.note.startswith("the arm moved"):
            return "the arm is at its rest pose and nothing carries it there: release it once someone holds the arm"
        return None

    def request_lowering(self) -> Response:
        """The operator asks a held arm to be lowered to its rest (at a tick boundary)."""
        refused = self.lowering_refused()
        if refused is not None or self.safe_stop is None:
            return Response("lower", False, self.state_name, refused or "no fault reaction holds the arm")
        self.safe_stop.lower_now()
        log.warning("reaction: lowering asked by the operator", state=self.state_name, t_s=self._t_s)
        for listener in self.reaction_listeners:
            listener(self.reaction)  # type: ignore[arg-type]
        return Response("lower", True, self.state_name)

    def request_release(self) -> Response:
        """The operator releases a held arm to someone holding it: the torque ramps to zero (at a tick boundary)."""
        stop = self.safe_stop
        if not self._reaction_running or stop is None:
            return Response("release", False, self.state_name, "no fault reaction holds the arm")
        stop.release()
        log.warning("reaction: release asked by the operator", state=self.state_name, t_s=self._t_s)
        return Response("release", True, self.state_name)

    def _react(self, faults: list[Fault], sample: Sample | None) -> None:
        """Decide the reaction to ``faults`` (with those already latched) and put it in force now."""
        if self.reaction is None:
            state = self.machine.state
            self._reaction_state = state if isinstance(state, StateSpec) else self._reaction_state
        drives = sample.drives if sample is not None else self._drives
        if self.reaction is not None and not self._reaction_running:
            # Off (or ended with the torque off): nothing is held any more, so nothing can be given back.
            drives = (DriveState.DISABLED,) * N_JOINTS
        plan = plan_reaction(faults, self._reaction_state.name, self.spec.fault_reactions, self.estop_wiring, drives)
        previous = self.reaction
        plan = escalate(previous, plan)
        if plan == previous:
            if self._reaction_running:
                self.monitor.grant(plan.joints_off, self._reaction_deadline_s)  # the new fault withdrew it
            return
        self.reaction = plan
        now = self._t_s
        if previous is None:
            self.reaction_started_s = now
        if plan.within_s is not None and (previous is None or previous.within_s is None):
            self._reaction_deadline_s = now + plan.within_s
        stop = self.safe_stop
        if not plan.holds or stop is None:
            self._stop_running("off")
        elif not self._reaction_running:
            support = self._support_model(self._reaction_state) if self._support_model is not None else None
            stop.arm(plan.reaction == "lower", plan.joints_off, support if plan.support == "model" else None,
                     self._reaction_deadline_s, self.monitor.last_finite_q())  # fmt: skip
            self._reaction_running = True
            self.signals.arm_held = True
            self._controller = stop
            # The reaction works within the limits of the state the fault was found in (FAIL's are 0 Nm).
            self._set_limits(self._reaction_state)
            self._needs_reset = sample is None  # no reading this tick: the stop takes over at the next one
            if sample is not None:
                try:
                    stop.reset(sample)
                except (ControlError, ValueError) as exc:  # cannot hold: off is all that is left
                    log.error("reaction: the safe stop cannot take over", error=str(exc), t_s=now)
                    self.reaction = plan = plan._replace(reaction="off")
                    self._stop_running(f"the safe stop could not take over: {exc}")
            if self._reaction_running:
                self.monitor.grant(plan.joints_off, self._reaction_deadline_s)
                self._stop_phase = stop.phase
        else:
            stop.escalate(plan.reaction == "lower", plan.joints_off, plan.support == "a_priori",
                          self._reaction_deadline_s)  # fmt: skip
            self.monitor.grant(plan.joints_off, self._reaction_deadline_s)
        log.warning(
            "reaction" if previous is None else "reaction escalated",
            reaction=plan.reaction,
            category=plan.category,
            joints_off=list(plan.joints_off),
            support=plan.support,
            within_s=plan.within_s,
            causes=list(plan.causes),
            state=self._reaction_state.name,
            t_s=now,
        )
        for listener in self.reaction_listeners:
            listener(plan)

    def _stop_running(self, why: str) -> None:
        """The reaction commands no torque (any more): withdraw the grant, drives off, the arm released."""
        self.monitor.withdraw()
        if self._reaction_running or self._controller is self.safe_stop:
            self._controller = None
        if self.machine.in_fail:
            self._set_fail_limits()
        self._reaction_running = False
        self.signals.arm_held = False
        self._stop_phase = None
        log.warning("reaction: torque off", why=why, state=self.state_name, t_s=self._t_s)

    def _follow_the_stop(self) -> None:
        """In the tick: log the safe stop's phases; end the reaction once the arm rests with the torque off."""
        stop = self.safe_stop
        if stop is None:
            return
        phase = stop.phase
        if phase is self._stop_phase:
            return
        self._stop_phase = phase
        log.warning("reaction phase", phase=phase.value, note=stop.note, state=self.state_name, t_s=self._t_s)
        if stop.finished:
            self._stop_running(stop.note or "the reaction ended")

    def _end_reaction(self, why: str) -> None:
        """The reaction is over (a test state's faults cleared, or a reset): the state's controller comes back."""
        if self._reaction_running:
            self._stop_running(why)
        self.monitor.withdraw()
        self.reaction = None
        self.reaction_started_s = None
        self._reaction_deadline_s = float("inf")
        state = self.machine.state
        self._controller = self.controllers[state.mode]
        self._needs_reset = self._controller is not None
        log.info("reaction ended", why=why, state=self.state_name, t_s=self._t_s)

    # --- events ---------------------------------------------------------------------------

    def fire(self, event: Event, origin: str = "operator") -> Response:
        """Apply one FSM event now (at a tick boundary) and log it; returns the response."""
        if origin != "fault":
            log.info("request", request=event.value, origin=origin, state=self.state_name, t_s=self._t_s)
        outcome = self.machine.request(event)
        if not outcome.accepted:
            log.warning(
                "refused",
                request=event.value,
                origin=origin,
                state=outcome.source,
                reason=outcome.reason,
                unmet=list(outcome.unmet),
                t_s=self._t_s,
            )
            return Response(event.value, False, outcome.source, outcome.reason, outcome.unmet)
        if event != Event.ACKNOWLEDGE:
            self._enter(self.machine.state, outcome)
            if self._fail_on_fault and self.monitor.faulted and not self.machine.in_fail:
                # Entered a state that fails on faults with one still latched (e.g. reset out of a test state).
                self.fire(Event.FAIL, "fault")
        return Response(event.value, True, self.state_name)

    def _acknowledged(self, outcome: Outcome) -> None:
        if self._on_fault_acknowledged is not None:
            # The drives' fault reset (CiA 402 bit 7 edge; lost drives brought back): a request the
            # backend carries out over the next ticks, never a wait in this one.
            self._on_fault_acknowledged()
        if self.machine.in_fail:
            self.signals.fault_acknowledged = True
            log.info(
                "fault acknowledged", state=outcome.source, faults=_fault_list(self.monitor.latched), t_s=self._t_s
            )
        else:  # a test state: what the test latched is cleared once its condition is gone
            remaining = self.monitor.clear()
            log.info("test fault acknowledged", state=outcome.source, remaining=_fault_list(remaining), t_s=self._t_s)

    # --- internals ------------------------------------------------------------------------

    def _log_flood_end(self, refused: int) -> None:
        log.warning(
            "requests refused: too many were waiting for the loop",
            refused=refused,
            limit=self.max_pending_requests,
            total_refused=self.refused_requests,
            t_s=self._t_s,
        )

    def _apply_requests(self) -> None:
        """Apply waiting requests in order: at most ``max_requests_per_tick``, and none after a state change."""
        requests = self._requests
        transitions = self.transitions
        for _ in range(self.max_requests_per_tick):
            if not requests or self.transitions != transitions:
                return
            action, ticket = requests.popleft()  # atomic in CPython; only the tick pops, so no lock
            try:
                response = action(self)
            except DarorError as exc:  # a request that cannot be applied is refused, never half-applied
                response = Response(ticket.request, False, self.state_name, str(exc))
                log.warning("refused", request=ticket.request, state=self.state_name, reason=str(exc), t_s=self._t_s)
            except Exception as exc:  # a bug in a request: the robot stops (a software fault), the loop goes on
                log.exception("request raised", request=ticket.request, state=self.state_name)
                response = Response(ticket.request, False, self.state_name, f"internal error: {exc!r}")
                self._own_fault(f"request {ticket.request!r} raised {exc!r}", self.signals.sample)
            ticket.resolve(response)

    def _route(self, faults: list[Fault], sample: Sample | None) -> None:
        """Faults of this tick: FAIL from a state that fails, the test's evidence in a test state; the reaction."""
        self._record(faults, sample)
        self._react(faults, sample)

    def _record(self, faults: list[Fault], sample: Sample | None) -> None:
        machine = self.machine
        if machine.in_fail:
            self.signals.fault_acknowledged = False  # a new fault needs its own acknowledgement
            log.error("fault in FAIL", faults=_fault_list(faults), t_s=self._t_s)
            return
        if self._fail_on_fault:
            log.error("fault", state=self.state_name, faults=_fault_list(faults), t_s=self._t_s)
            self._reaction_state = machine.state if self.reaction is None else self._reaction_state  # type: ignore[assignment]
            self.fire(Event.FAIL, "fault")
            return
        for fault in faults:
            if fault.kind == FaultKind.ESTOP and sample is not None:
                pressed = [b for b, on in zip(ESTOP_BUTTONS, sample.estop, strict=False) if on]
                self.signals.estop_tested.update(pressed)
                log.info(
                    "e-stop test",
                    state=self.state_name,
                    buttons=[b.value for b in pressed],
                    tested=sorted(b.value for b in self.signals.estop_tested),
                    t_s=self._t_s,
                )
            else:
                log.warning(
                    "fault in an e-stop test state: met by its reaction until acknowledged, no FAIL",
                    state=self.state_name,
                    fault=fault.as_dict(),
                    t_s=self._t_s,
                )

    def _enter(self, state: StateSpec | FailSpec, outcome: Outcome | None) -> None:
        """Switch limits and controller to ``state`` (called once per state change)."""
        signals = self.signals
        if outcome is not None and outcome.event == Event.RESET:
            if outcome.source == self.spec.fail.name:
                self.monitor.clear()
                signals.fault_acknowledged = False
            if self.reaction is not None:
                self._end_reaction(f"reset from {outcome.source}")
            signals.forget_installation()
        else:
            signals.forget_visit()
        if isinstance(state, StateSpec):
            self._fail_on_fault = state.fail_on_fault
            self._set_limits(state)
        elif not self._reaction_running:  # a reaction keeps the limits of the state it began in
            self._fail_on_fault = True
            self._set_fail_limits()
        else:
            self._fail_on_fault = True
        if self._reaction_running:  # the reaction goes on holding the arm, whatever the state
            self._controller = self.safe_stop
        else:
            self._controller = self.controllers[state.mode]
            self._needs_reset = self._controller is not None
        if outcome is not None:
            self.transitions += 1
            log.info(
                "transition",
                trigger=outcome.event.value,
                source=outcome.source,
                dest=state.name,
                mode=state.mode,
                t_s=self._t_s,
            )
            for listener in self.listeners:
                listener(state, outcome)
        sample = signals.sample
        if self._needs_reset and sample is not None and self.monitor.torque_permitted:
            self._reset_controller(sample)

    def _set_limits(self, state: StateSpec) -> None:
        limits = self.device_limits.for_state(state.limits.torque_nm, state.limits.velocity_rad_s)
        isb = self.signals.isb_limits if state.enforce_isb else None
        for listener in self.limits_listeners:
            listener(isb)
        if isb is None:
            self.monitor.set_limits(limits.with_isb(None))
            return
        if self._isb_function is None:
            raise ConfigurationError(f"state {state.label} enforces ISB limits but the supervisor has no ISB function")
        self.monitor.set_limits(limits.with_isb(isb, self.isb_margin_rad), self._isb_function(isb))

    def _set_fail_limits(self) -> None:
        self.monitor.set_limits(self.device_limits.for_state(0.0, float(self.device_limits.max_velocity_rad_s.max())))

    def refresh_limits(self) -> None:
        """Apply the current state's limits again (after the pilot's ISB limits changed)."""
        state = self.machine.state
        if isinstance(state, StateSpec):
            self._set_limits(state)

    def _reset_controller(self, sample: Sample) -> None:
        controller = self._controller
        self._needs_reset = False
        if controller is None:
            return
        try:
            controller.reset(sample)
        except ControlError as exc:
            self._own_fault(f"{type(controller).__name__} cannot start: {exc}", sample)

    def _own_fault(self, message: str, sample: Sample | None) -> None:
        """A software fault the supervisor found: latched, in the tick's faults, routed now."""
        fault = self.monitor.report(FaultKind.SOFTWARE, self._t_s, message)
        if fault is not None:
            self._tick_faults.append(fault)
            self._route([fault], sample)


def _fault_list(faults: list[Fault]) -> list[dict[str, object]]:
    return [f.as_dict() for f in faults]
