"""Build the operator's :class:`~daror_runtime.session.status.RuntimeStatus` from a session's parts.

Read from any thread, between ticks or while the loop runs (values may be one tick old).
Collections the tick changes are copied first in one C-level call (atomic under the GIL), so a
snapshot never iterates one the loop is changing.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from daror_runtime.fsm.guards import GUARDS
from daror_runtime.fsm.machine import OPERATOR_EVENTS
from daror_runtime.fsm.signals import ESTOP_BUTTONS, SessionSignals
from daror_runtime.fsm.spec import StateSpec
from daror_runtime.session.core import SessionCore
from daror_runtime.session.provenance import session_pilot
from daror_runtime.session.status import (
    EventGate,
    GuardState,
    JointReadings,
    LoopStatus,
    ModelStatus,
    ReactionStatus,
    RuntimeStatus,
)
from hal.interface import Command, Sample
from hal.isb import IsbLimits


def snapshot(core: SessionCore) -> RuntimeStatus:
    """What the operator sees of ``core`` now."""
    supervisor = core.supervisor
    state = supervisor.state
    signals = core.signals
    sample = signals.sample
    machine = supervisor.machine
    gates = {}
    for event in OPERATOR_EVENTS:
        transition = machine.table.get((state.name, event))
        if transition is None:
            gates[event.value] = EventGate(event.value, False, why_not=machine.why_not(event))
            continue
        guards = tuple(_guard_state(g, signals) for g in transition.guards)
        gates[event.value] = EventGate(event.value, True, guards)
    run = core.modes.identification.run
    compensation = core.modes.compensation
    loop = core.loop
    stats = loop.stats
    pacing = core.clock.pacing
    progress = core.progress
    return RuntimeStatus(
        session_id=core.session_id,
        pilot=session_pilot(core),
        t_s=sample.t_s if sample is not None else None,
        state=state.name,
        number=state.number if isinstance(state, StateSpec) else None,
        superstate=state.superstate if isinstance(state, StateSpec) else None,
        mode=state.mode,
        description=state.description,
        estop_test_state=isinstance(state, StateSpec) and not state.fail_on_fault,
        gates=gates,
        faults=[f.as_dict() for f in core.monitor.latched],
        estop_pressed={
            b.value: bool(sample is not None and len(sample.estop) > i and sample.estop[i])
            for i, b in enumerate(ESTOP_BUTTONS)
        },
        estop_tested=sorted(b.value for b in set(signals.estop_tested)),  # copied at C level: the tick may add
        confirmed=sorted(c.value for c in set(signals.confirmed)),
        joints=None if sample is None else _joint_readings(sample, loop.last_command),
        model=_model_status(core),
        model_refused=progress.last_model_refused,
        support_level=compensation.support_level,
        delivered_support_level=compensation.delivered_support_level,
        handover_nm=tuple(float(v) for v in compensation.handover.remaining_nm)
        if compensation.handover.active
        else (0.0,) * 4,
        isb_limits_deg=None if signals.isb_limits is None else _isb_degrees(signals.isb_limits),
        isb_margin_deg=float(core.settings.isb_margin_deg),
        rom_recording=core.rom is not None,
        identification_running=None
        if run is None or sample is None
        else {"kind": run.kind, "elapsed_s": sample.t_s - run.t0_s, "duration_s": run.duration_s},
        identification_saved={k: str(v) for k, v in dict(signals.identification_saved).items()},
        last_identification=progress.last_identification,
        jobs_pending=core.jobs.pending,
        last_error=progress.last_error,
        loop=LoopStatus(
            clock=core.clock.name,
            rate_hz=core.hal.rate_hz,
            ticks=stats.ticks,
            overruns=stats.overruns,
            missed_deadlines=stats.missed_deadlines,
            worst_lateness_ms=stats.worst_lateness_s * 1e3,
            tick_work_mean_us=stats.mean_work_s * 1e6,
            tick_work_max_us=stats.worst_work_s * 1e6,
            dropped_rows=loop.dropped_rows,
            stalls=0 if pacing is None else pacing.stalls,
            lag_ms=0.0 if pacing is None else pacing.lag_s * 1e3,
            behind_ms=0.0 if pacing is None else pacing.behind_s * 1e3,
        ),
        transitions=supervisor.transitions,
        a_priori_includes_dummy_arm=core.settings.dummy_arm,
        reaction=_reaction_status(core),
        online=core.online.as_list(),
        comparison=None if core.compare is None else core.compare.status(),
    )


def _reaction_status(core: SessionCore) -> ReactionStatus | None:
    supervisor = core.supervisor
    plan = supervisor.reaction
    if plan is None:
        return None
    stop = core.safe_stop
    running = supervisor.reaction_running
    return ReactionStatus(
        reaction=plan.reaction,
        category=plan.category,
        causes=plan.causes,
        joints_off=plan.joints_off,
        support=plan.support,
        arm_held=running,
        lowering_refused=supervisor.lowering_refused() if running else "no fault reaction holds the arm",
        phase=stop.phase.value if running or stop.finished else None,
        note=stop.note if running or stop.finished else "",
        since_t_s=supervisor.reaction_started_s,
        rest=core.settings.rest.support,
    )


def _isb_degrees(limits: IsbLimits) -> dict[str, tuple[float, float]]:
    names = ("elevation", "horizontal_rotation", "axial_rotation", "elbow")
    return {name: (r.lower_deg, r.upper_deg) for name, r in zip(names, limits.ranges, strict=True)}


def _joint_readings(sample: Sample, last_command: Command) -> JointReadings:
    return JointReadings(
        q_deg=tuple(float(np.degrees(v)) for v in sample.q_rad),
        dq_deg_s=tuple(float(np.degrees(v)) for v in sample.dq_rad_s),
        spring_torque_nm=tuple(float(v) for v in sample.tau_nm),
        motor_command_nm=tuple(float(v) for v in last_command.motor_torque_nm),
        drives=tuple(d.name.lower() for d in sample.drives),
    )


def _guard_state(name: str, signals: SessionSignals) -> GuardState:
    guard = GUARDS[name]
    holds = bool(guard.read(signals))
    why = guard.explain(signals) if not holds and guard.explain is not None else None
    return GuardState(name, guard.description, holds, why)


def _model_status(core: SessionCore) -> ModelStatus | None:
    summary = core.progress.last_model
    if summary is None or core.modes.compensation.model is None:
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
        validation_data=summary["validation_data"]["description"] if "validation_data" in summary else None,
        conservative=summary.get("conservative"),
        closed_path_energy_j=tuple(summary["closed_path_energy_j"]) if "closed_path_energy_j" in summary else None,
        nonconservative_confirmed=bool(summary.get("nonconservative_confirmed", False)),
        validation_extrapolation=extrapolation_text(summary.get("extrapolation")),
    )


def extrapolation_text(extrapolation: dict[str, Any] | None) -> str | None:
    """``106 of 166 validation points outside the model's training range: RMSE 0.437 Nm inside, 0.423 Nm outside``."""
    if extrapolation is None:
        return None
    inside, outside = extrapolation["rmse_inside"], extrapolation["rmse_outside"]
    return (
        f"{extrapolation['outside']} of {extrapolation['points']} validation points outside the model's training "
        f"range: RMSE {'-' if inside is None else f'{inside:.3g} Nm'} inside, "
        f"{'-' if outside is None else f'{outside:.3g} Nm'} outside"
    )
