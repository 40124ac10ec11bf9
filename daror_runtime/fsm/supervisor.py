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
from typing import Any

import structlog

from daror_runtime.control.base import ControlError, Controller
from daror_runtime.errors import ConfigurationError, DarorError
from daror_runtime.fsm.guards import GUARDS
from daror_runtime.fsm.machine import Event, Outcome, SafetyMachine
from daror_runtime.fsm.modes import MODES
from daror_runtime.fsm.signals import ESTOP_BUTTONS, SessionSignals
from daror_runtime.fsm.spec import FailSpec, FsmSpec, StateSpec
from daror_runtime.safety.faults import Fault, FaultKind
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import IsbFunction, SafetyMonitor
from hal.interface import Sample
from hal.isb import IsbLimits

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

    def post(self, request: str, action: Action, *, essential: bool = False) -> Ticket:
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
        """
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
        if self._was_faulted and not faulted:
            self._needs_reset = True  # torque comes back: start the controller from the present
        self._was_faulted = faulted
        if self._needs_reset and sample is not None and not faulted:
            self._reset_controller(sample)
        return self._controller

    def on_late_faults(self, sample: Sample | None, faults: list[Fault]) -> None:
        """Faults the loop found after :meth:`on_tick` (controller, recorder, HAL write): same tick."""
        self._route(faults, sample)

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
        """Faults of this tick: FAIL from a state that fails; the test's evidence in a test state."""
        machine = self.machine
        if machine.in_fail:
            self.signals.fault_acknowledged = False  # a new fault needs its own acknowledgement
            log.error("fault in FAIL", faults=_fault_list(faults), t_s=self._t_s)
            return
        if self._fail_on_fault:
            log.error("fault", state=self.state_name, faults=_fault_list(faults), t_s=self._t_s)
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
                    "fault in an e-stop test state: torque off until acknowledged, no FAIL",
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
            signals.forget_installation()
        else:
            signals.forget_visit()
        if isinstance(state, StateSpec):
            self._fail_on_fault = state.fail_on_fault
            self._set_limits(state)
        else:
            self._fail_on_fault = True
            self.monitor.set_limits(
                self.device_limits.for_state(0.0, float(self.device_limits.max_velocity_rad_s.max()))
            )
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
        if self._needs_reset and sample is not None and not self.monitor.faulted:
            self._reset_controller(sample)

    def _set_limits(self, state: StateSpec) -> None:
        limits = self.device_limits.for_state(state.limits.torque_nm, state.limits.velocity_rad_s)
        isb = self.signals.isb_limits if state.enforce_isb else None
        if isb is None:
            self.monitor.set_limits(limits.with_isb(None))
            return
        if self._isb_function is None:
            raise ConfigurationError(f"state {state.label} enforces ISB limits but the supervisor has no ISB function")
        self.monitor.set_limits(limits.with_isb(isb, self.isb_margin_rad), self._isb_function(isb))

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
