"""The drift test in a session (issue 29, part 2; :mod:`daror_runtime.online.drift`).

:func:`request_drift_test` is the operator's request: checked and started at a tick boundary (the
supervisor applies requests in the tick). :func:`service_drift` runs in the service between ticks:
it watches the drift, asks for the catch (the FSM's ``revert`` into the state whose mode holds the
pose, origin ``drift test``: the FSM decides, the hold obeys), then measures the held springs.
Whatever else happens (a fault, a reaction, another transition) abandons the test with its reason;
the safety functions act as always.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import structlog

from daror_runtime.fsm.machine import Event
from daror_runtime.fsm.spec import StateSpec
from daror_runtime.online.drift import DRIFT_MAX_DEG, MARGIN_DEG, DriftPhase, DriftTest
from daror_runtime.session.events import AnnouncementKind
from daror_runtime.session.online import model_label

if TYPE_CHECKING:
    from daror_runtime.fsm.supervisor import FsmSupervisor, Response, Ticket
    from daror_runtime.session.core import SessionCore

log = structlog.get_logger(__name__)

#: The arm must have been still this long before a test starts (s; the online indicators' judgement).
STILL_BEFORE_S = 0.3
#: The catch must have the arm within this long of being asked for (s of robot time), else the test is abandoned.
CATCH_TIMEOUT_S = 0.5


def _catching_state(supervisor: FsmSupervisor) -> str | None:
    """Where ``revert`` leads from the current state, if that state holds the pose (mode ``hold``)."""
    transition = supervisor.machine.table.get((supervisor.state.name, Event.REVERT))
    if transition is None:
        return None
    destination = supervisor.spec.state(transition.dest)
    return destination.name if destination.mode == "hold" else None


def _why_not(core: SessionCore, supervisor: FsmSupervisor) -> str | None:
    """Why a drift test cannot start now (one sentence), or None."""
    state = supervisor.state
    compensation = core.modes.compensation
    sample = core.signals.sample
    if not isinstance(state, StateSpec) or state.mode != "compensation" or _catching_state(supervisor) is None:
        return (
            f"a drift test runs in a compensation state whose revert holds the arm (compensation), not in {state.name}"
        )
    if compensation.model is None:
        return "no model supports the arm"
    if core.drift is not None and core.drift.phase in (DriftPhase.DRIFTING, DriftPhase.CATCHING, DriftPhase.HOLDING):
        return "a drift test is under way"
    if supervisor.reaction is not None or core.monitor.faulted:
        return "a fault is latched or its reaction is under way"
    if compensation.support_level != 1.0 or compensation.delivered_support_level != 1.0:
        return "the model's whole support is tested: set support 1.0 and let it ramp there first"
    if compensation.handover.active:
        return "the entry's handover still adds support: let the pilot move the arm once first"
    record = core.online
    indicators = record.by_model.get(record.label) if record.label is not None else None
    if sample is None or indicators is None or indicators.still_for_s(sample.t_s) < STILL_BEFORE_S:
        return f"the arm must be still for {STILL_BEFORE_S:g} s first (the pilot holding it where the test begins)"
    margin = float(np.deg2rad(MARGIN_DEG))
    description = core.description
    q = np.asarray(sample.q_rad, dtype=float)
    if np.any(q < description.lower_limits_rad + margin) or np.any(q > description.upper_limits_rad - margin):
        return f"the arm must be {MARGIN_DEG:g} deg inside the joints' limits"
    limits = core.signals.isb_limits
    if limits is not None:
        isb = limits.for_box_check(core.shoulder.isb_from_q(q))
        if np.any(isb < limits.lower_rad + margin) or np.any(isb > limits.upper_rad - margin):
            return f"the arm must be {MARGIN_DEG:g} deg inside the pilot's ISB limits"
    return None


def request_drift_test(core: SessionCore) -> Ticket:
    """The operator asks for a drift test here (see :mod:`daror_runtime.online.drift`)."""
    from daror_runtime.fsm.supervisor import Response

    def apply(supervisor: FsmSupervisor) -> Response:
        why = _why_not(core, supervisor)
        if why is not None:
            return core.refuse("drift test", why)
        sample = core.signals.sample
        model = core.modes.compensation.model
        if sample is None or model is None:  # _why_not has seen both
            return core.refuse("drift test", "no sample or no model")
        core.drift = DriftTest(model_label(core, model), sample.t_s, sample.q_rad)
        log.info("drift test started", state=supervisor.state_name, model=core.drift.model, t_s=sample.t_s)
        return Response("drift test", True, supervisor.state_name)

    log.info("request", request="drift test", origin="operator", state=core.supervisor.state_name)
    return core.supervisor.post("drift test", apply)


def _abandon(core: SessionCore, test: DriftTest, why: str) -> None:
    test.abandon(why)
    log.warning("drift test abandoned", reason=why, t_s=core.t_s())
    core.announcements.announce(AnnouncementKind.SESSION, f"drift test abandoned: {why}", core.t_s())


def service_drift(core: SessionCore) -> None:
    """Between ticks: watch a drift test under way, ask for the catch, measure the hold."""
    test = core.drift
    if test is None or test.phase in (DriftPhase.DONE, DriftPhase.ABANDONED):
        return
    supervisor = core.supervisor
    sample = core.signals.sample
    if sample is None:
        return
    if supervisor.reaction is not None or core.monitor.faulted:
        _abandon(core, test, "a fault: its reaction acts")
        return
    state = supervisor.state
    if test.phase == DriftPhase.DRIFTING:
        if state.mode != "compensation":
            _abandon(core, test, f"the state changed to {state.name}")
            return
        why = test.observe_drift(sample.t_s, sample.q_rad)
        if why is not None:
            test.catch(sample.t_s, why)
            supervisor.post_event(Event.REVERT, "drift test")  # the FSM's revert: the hold takes the arm
            log.info("drift test: catch", why=why, t_s=sample.t_s)
        return
    if test.phase == DriftPhase.CATCHING:
        if state.mode == "hold":
            test.held(sample.t_s, sample.q_rad)
        elif sample.t_s - (test.t_start_s + test.drift_s) > CATCH_TIMEOUT_S:
            _abandon(core, test, f"the catch did not come (state {state.name})")
        return
    if state.mode != "hold":
        _abandon(core, test, f"the hold ended (state {state.name})")
        return
    model = core.modes.compensation.model
    if model is None:
        _abandon(core, test, "no model")
        return
    springs = core.modes.compensation.torque.spring_torque_nm(sample)
    if test.observe_hold(sample.t_s, springs, np.asarray(model.torque(sample.q_rad), dtype=float)) and test.result:
        result = test.result
        core.online.drift_tests.append(result)
        log.info("drift test", **result.as_dict())
        unsupported = " ".join(f"{v:.2f}" for v in result.unsupported_nm)
        drift = " ".join(f"{v:.1f}" for v in result.drift_deg)
        core.announcements.announce(
            AnnouncementKind.SESSION,
            f"drift test ({result.model}): caught after {result.drift_s:.2f} s ({result.why_caught}; at most "
            f"{DRIFT_MAX_DEG:g} deg), drift {drift} deg; unsupported torque {unsupported} Nm; "
            f"advance returns to compensation",
            sample.t_s,
        )


__all__ = ["request_drift_test", "service_drift"]
