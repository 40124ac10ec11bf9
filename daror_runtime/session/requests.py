"""The operator's requests, as the session applies them (the facade :class:`~daror_runtime.runtime.Runtime` calls these).

Every request follows one pattern: what may take long or may fail on the operator's input is
done and checked here, in the caller's thread (a :class:`~daror_runtime.session.core.RequestRefusedError`
or an input error comes back at once); what changes the robot is an ``apply`` function the
supervisor runs at the next tick boundary, where the FSM decides, returning a
:class:`~daror_runtime.fsm.supervisor.Response` (accepted, or refused with the reason, logged).
Slow work (saving identification data, fitting, validating) runs as a job and hands its result
back through another such request.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import structlog

from daror_runtime.control.base import ControlError, ControlSettingError
from daror_runtime.data.recorder import Recorder
from daror_runtime.errors import DarorError, InputError
from daror_runtime.fsm.guards import GUARDS
from daror_runtime.fsm.machine import Event
from daror_runtime.fsm.signals import Checklist
from daror_runtime.fsm.spec import StateSpec
from daror_runtime.fsm.supervisor import FsmSupervisor, Response, Ticket
from daror_runtime.identification.protocol import IdentificationRun, let_the_writer_catch_up
from daror_runtime.logs import set_session_pilot
from daror_runtime.models.compare import cvf_models
from daror_runtime.models.registry import kind_entry, kind_names
from daror_runtime.session.core import RequestRefusedError, SessionCore
from daror_runtime.session.events import AnnouncementKind
from daror_runtime.session.identification import (
    RecordingSignalMapError,
    abandon_run,
    finish_run,
    prepare_run,
    session_waypoints,
)
from daror_runtime.session.provenance import (
    ValidationOrigin,
    record_provenance,
    session_pilot,
    session_robot,
    validation_origin,
)
from daror_runtime.session.rom import RomEnvelope
from daror_runtime.session.training import TrainedModel, read_model_candidate, train_model, validate_candidate
from daror_runtime.util.atomic import write_text_atomic
from hal.isb import IsbLimits, isb_limits_yaml

log = structlog.get_logger(__name__)

# --- the FSM's events and checklists ---------------------------------------------------------


def request_event(core: SessionCore, event: Event | str) -> Ticket:
    """advance, revert, reset or acknowledge (the operator's buttons).

    Raises:
        ValueError: not an event name.
        RequestRefusedError: ``fail`` (faults and e-stops fail the robot, never the operator).
    """
    event = Event(event)
    if event == Event.FAIL:
        raise RequestRefusedError("fail is not an operator request: faults and e-stops fail the robot")
    return core.supervisor.post_event(event, "operator")


def confirm(core: SessionCore, checklist: Checklist | str) -> Ticket:
    """The operator confirms a checklist of the current state (settings, installation, safety_experience, ...).

    Raises:
        RequestRefusedError: not a checklist name.
    """
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
            return core.refuse(f"confirm {item.value}", f"state {state.name} has no {item.value} checklist")
        if item == Checklist.A_PRIORI_MODEL:
            refusal = _use_a_priori(core, supervisor)
            if refusal is not None:
                return refusal
        supervisor.signals.confirmed.add(item)
        log.info("checklist confirmed", checklist=item.value, state=state.name, t_s=core.t_s())
        return Response(f"confirm {item.value}", True, state.name)

    log.info("request", request=f"confirm {item.value}", origin="operator", state=core.supervisor.state_name)
    return core.supervisor.post(f"confirm {item.value}", apply)


def _use_a_priori(core: SessionCore, supervisor: FsmSupervisor) -> Response | None:
    """At a tick boundary: the operator approved the A Priori model; compensation uses it unless a validated model is in use."""
    selected = supervisor.signals.model
    if selected is not None and selected.validated:
        return core.refuse(
            f"confirm {Checklist.A_PRIORI_MODEL.value}",
            f"the validated model {selected.name} ({selected.kind}) is in use; the A Priori model is not needed",
        )
    core.modes.compensation.model = core.a_priori
    core.a_priori_confirmed = True  # for this pilot, this session (a blind comparison may use it again)
    # not validated on this pilot: its error moves a limp arm, slowly (docs/safety.md)
    core.modes.compensation.damping_nms_per_rad = core.settings.unvalidated_model_damping_nms_per_rad
    core.progress.last_model = a_priori_summary(core)
    log.info("model in use", **core.progress.last_model, state=supervisor.state_name, t_s=core.t_s())
    return None


def a_priori_summary(core: SessionCore) -> dict[str, Any]:
    """The A Priori model as the status shows a model in use."""
    return {
        "name": core.a_priori.name,
        "kind": core.a_priori.kind,
        "path": None,
        "validation_rmse_nm": None,
        "validation_rmse_per_joint_nm": None,
        "validated": False,
        "approved_by": "operator (A Priori model confirmed)",
        "includes_dummy_arm": core.settings.dummy_arm,
    }


def set_support(core: SessionCore, level: float) -> Ticket:
    """Set the compensation support level in [0, 1] (the delivered level ramps to it)."""

    def apply(supervisor: FsmSupervisor) -> Response:
        try:
            core.modes.compensation.support_level = level
        except ControlSettingError as exc:
            return core.refuse(f"support {level}", str(exc))
        core.history.support(level)
        log.info("support level set", level=level, state=supervisor.state_name, t_s=core.t_s())
        return Response(f"support {level}", True, supervisor.state_name)

    log.info("request", request=f"support {level}", origin="operator", state=core.supervisor.state_name)
    return core.supervisor.post(f"support {level}", apply)


# --- the pilot ----------------------------------------------------------------------------------


def name_pilot(core: SessionCore, code: str) -> Ticket:
    """Name the session's pilot by his code (``pilot CODE``): until the state that needs him is left.

    The state whose advance needs ``pilot_named`` (``settings``) is the last where he may be named
    or named again, and only while nothing of this session belongs to the pilot named before (a
    model validated for him). Every file the session writes from then on, its audit trail and the
    lab's records carry the code.

    Raises:
        RequestRefusedError: ``code`` is not a pilot's code (letters, digits, ``_ . -``; at most 32).
    """
    from daror_runtime.records.codes import PILOT_CODE_PATTERN  # the pattern only: no database here

    if re.match(PILOT_CODE_PATTERN, code) is None:
        raise RequestRefusedError(
            f"pilot {code!r}: not a code; expected letters, digits, '_', '.', '-' (at most 32), e.g. P-007; never a name"
        )
    naming = next((s for s in core.spec.states if "pilot_named" in s.guards.advance), None)

    def apply(supervisor: FsmSupervisor) -> Response:
        state = supervisor.state
        if naming is None:
            return core.refuse(f"pilot {code}", "this session's FSM spec has no state that names the pilot")
        if not isinstance(state, StateSpec) or state.number > naming.number:
            return core.refuse(
                f"pilot {code}",
                f"the pilot is named before {naming.name} is left, not in {state.name}; reset to name another",
            )
        previous = core.signals.pilot
        if core.signals.model is not None and previous != code:
            return core.refuse(
                f"pilot {code}",
                f"a model was validated in this session for pilot {session_pilot(core)}; reset the session to name another",
            )
        core.signals.pilot = code
        set_session_pilot(code)
        log.info("pilot named", pilot=code, previous=previous, state=supervisor.state_name)
        return Response(f"pilot {code}", True, supervisor.state_name)

    log.info("request", request=f"pilot {code}", origin="operator", state=core.supervisor.state_name)
    return core.supervisor.post(f"pilot {code}", apply)


# --- the pilot's range of motion ---------------------------------------------------------------


def rom_start(core: SessionCore) -> Ticket:
    """Start recording the pilot's range of motion (in a state that needs the ISB limits recorded)."""
    envelope = RomEnvelope(core.shoulder, IsbLimits().horizontal_free_below_rad)

    def apply(supervisor: FsmSupervisor) -> Response:
        refusal = _rom_state_refusal(core, "rom start")
        if refusal is not None:
            return refusal
        if core.loop.recorder is not None:
            return core.refuse("rom start", "a recording is already running")
        core.rom = envelope
        core.loop.recorder = envelope
        log.info("range of motion recording started", state=supervisor.state_name, t_s=core.t_s())
        return Response("rom start", True, supervisor.state_name)

    log.info("request", request="rom start", origin="operator", state=core.supervisor.state_name)
    return core.supervisor.post("rom start", apply)


def rom_stop(core: SessionCore) -> Ticket:
    """Stop the recording; the recorded range becomes the pilot's ISB limits (or is refused as too small)."""

    def apply(supervisor: FsmSupervisor) -> Response:
        envelope = core.rom
        if envelope is None:
            return core.refuse("rom stop", "no range of motion is being recorded")
        core.rom = None
        if core.loop.recorder is envelope:
            core.loop.recorder = None
        try:
            limits = envelope.limits(IsbLimits(), core.settings.rom_min_range_deg)
        except InputError as exc:
            return core.refuse("rom stop", str(exc))
        return _set_isb_limits(core, supervisor, limits, f"recorded over {envelope.samples} ticks")

    log.info("request", request="rom stop", origin="operator", state=core.supervisor.state_name)
    return core.supervisor.post("rom stop", apply)


def set_isb_limits(core: SessionCore, limits: IsbLimits, source: str = "entered") -> Ticket:
    """Use ``limits`` (e.g. from a clinical assessment file) as the pilot's ISB limits."""

    def apply(supervisor: FsmSupervisor) -> Response:
        refusal = _rom_state_refusal(core, "isb limits")
        return refusal if refusal is not None else _set_isb_limits(core, supervisor, limits, source)

    log.info("request", request="isb limits", origin="operator", state=core.supervisor.state_name, source=source)
    return core.supervisor.post("isb limits", apply)


def _rom_state_refusal(core: SessionCore, request: str) -> Response | None:
    state = core.supervisor.state
    if isinstance(state, StateSpec) and "isb_limits_recorded" in state.guards.advance:
        return None
    return core.refuse(
        request, f"the pilot's ISB limits are recorded in a state that requires them, not in {state.name}"
    )


def _set_isb_limits(core: SessionCore, supervisor: FsmSupervisor, limits: IsbLimits, source: str) -> Response:
    rest = core.settings.rest
    outside = rest.outside(limits)
    if outside:
        # Every lowering ends at the rest pose: limits that exclude it would leave a fault nowhere to lower to.
        return core.refuse(
            "isb limits",
            f"the rest pose of the session settings ({rest.support}: "
            + ", ".join(f"{v:g}" for v in rest.pose_isb_deg)
            + f" deg) lies outside these limits by more than {rest.tolerance_deg:g} deg ("
            + "; ".join(outside)
            + "): a fault's lowering could not end there; set rest.pose_isb_deg in the session settings to where "
            "the pilot's arm rests inside his range",
        )
    supervisor.signals.isb_limits = limits
    supervisor.refresh_limits()
    ranges = {
        name: [round(r.lower_deg, 1), round(r.upper_deg, 1)]
        for name, r in zip(("elevation", "horizontal", "axial", "elbow"), limits.ranges, strict=True)
    }
    log.info("ISB limits recorded", source=source, limits_deg=ranges, state=supervisor.state_name, t_s=core.t_s())
    _keep_isb_limits(core, limits, source)
    return Response("isb limits", True, supervisor.state_name, detail=limits)


def _keep_isb_limits(core: SessionCore, limits: IsbLimits, source: str) -> None:
    """A job writes the limits the session uses to ``SESSION/isb_limits.yaml`` (``rom load`` reads it next time)."""
    path = core.session_dir / "isb_limits.yaml"
    pilot = session_pilot(core) or "(no pilot named)"
    comment = (
        f"ISB limits of pilot {pilot}, session {core.session_id}, robot {session_robot(core)}: {source}\n"
        "degrees; the monitor allows isb_margin_deg (session settings) beyond each (docs/isb_limits.md)"
    )

    def job() -> None:
        write_text_atomic(path, isb_limits_yaml(limits, comment))
        log.info("ISB limits saved", path=str(path))

    core.jobs.submit("save isb limits", job)


# --- a fault's reaction ---------------------------------------------------------------------


def lower_arm(core: SessionCore) -> Ticket:
    """In FAIL (or a test state) with the arm held: lower it to its rest pose (planned outside the tick)."""
    log.info("request", request="lower", origin="operator", state=core.supervisor.state_name)
    return core.supervisor.post("lower", lambda supervisor: supervisor.request_lowering())


def release_arm(core: SessionCore) -> Ticket:
    """With the arm held by a reaction and someone holding it: the torque ramps to zero (docs/safety.md)."""
    log.info("request", request="release", origin="operator", state=core.supervisor.state_name)
    return core.supervisor.post("release", lambda supervisor: supervisor.request_release())


# --- identification ------------------------------------------------------------------------


def identify(core: SessionCore, kind: str) -> Ticket:
    """Start a training or validation run of the protocol (state with the identification mode).

    The trajectory and its controller are built here, in the caller's thread.

    Raises:
        RequestRefusedError: not in an identification state, no ISB limits, a run already going.
        TrajectoryError: the trajectory leaves the pilot's limits.
    """
    if kind not in ("training", "validation"):
        raise RequestRefusedError(f"unknown identification run {kind!r}; expected training or validation")
    state = core.supervisor.state
    if not isinstance(state, StateSpec) or state.mode != "identification":
        raise RequestRefusedError(
            f"identification runs only in a state with the identification mode, not in {state.name}"
        )
    limits = core.signals.isb_limits
    if limits is None:
        raise RequestRefusedError("the pilot's ISB limits are not recorded")
    if core.modes.identification.running or core.collecting:
        raise RequestRefusedError("an identification run is already going; stop it or wait for it")
    sample = core.signals.sample
    if sample is None:
        raise RequestRefusedError("no sample from the hardware yet")
    waypoints, outside = session_waypoints(core.settings.identification, limits, core.description)
    run = prepare_run(
        kind, core.description, sample.q_rad, waypoints, limits, core.settings.identification,
        core.a_priori, core.dt_s, core.session_dir,
    )  # fmt: skip
    # Load its compiled kernels here, not in the tick that starts the run (5 ms measured);
    # the start resets it again from that tick's sample.
    run.controller.reset(sample)
    run.controller.update(sample, core.dt_s)
    log.info("request", request=f"identify {kind}", origin="operator", waypoints=len(waypoints), outside_limits=outside)

    def apply(supervisor: FsmSupervisor) -> Response:
        now = supervisor.signals.sample
        current = supervisor.state
        reason = None
        if not isinstance(current, StateSpec) or current.mode != "identification":
            reason = f"the state changed to {current.name}"
        elif core.monitor.faulted or now is None:
            reason = "a fault is latched"
        elif core.loop.recorder is not None:
            reason = "a recording is already running"
        if reason is None and now is not None:
            try:
                core.modes.identification.start(run, now)
            except ControlError as exc:
                reason = str(exc)
        if reason is not None:
            core.jobs.submit("abandon identification", lambda: abandon_run(run, reason))
            return core.refuse(f"identify {kind}", reason)
        core.loop.recorder = run.recorder
        log.info("identification started", kind=kind, robot_s=round(run.duration_s, 1), t_s=core.t_s())
        return Response(f"identify {kind}", True, supervisor.state_name, detail=run.duration_s)

    return core.supervisor.post(f"identify {kind}", apply)


def stop_identification(core: SessionCore) -> Ticket:
    """Stop a run: the robot holds where it is; the recording is kept, no dataset is written."""

    def apply(supervisor: FsmSupervisor) -> Response:
        sample = supervisor.signals.sample
        mode = core.modes.identification
        if not mode.running or sample is None:
            return core.refuse("stop identification", "no identification run is going")
        run = mode.stop(sample)
        core.loop.recorder = None
        if run is not None:
            core.jobs.submit("abandon identification", lambda: abandon_run(run, "stopped by the operator"))
        return Response("stop identification", True, supervisor.state_name)

    log.info("request", request="stop identification", origin="operator", state=core.supervisor.state_name)
    return core.supervisor.post("stop identification", apply)


def collect_finished_run(core: SessionCore) -> None:
    """Between ticks: a run whose trajectory ended is detached at a tick boundary and its data saved in a job."""
    mode = core.modes.identification
    finished = mode.finished_run
    if finished is None or core.collecting:
        return
    mode.finished_run = None
    core.collecting = True
    core.supervisor.post("identification finished", lambda supervisor: _collect(core, finished), essential=True)


def keep_up_with_the_recorder(core: SessionCore, n: int) -> None:
    """Lock-step only, every 500 ticks: let the recorder's writer catch up (virtual time may wait; real time may not)."""
    recorder = core.loop.recorder
    if n % 500 == 0 and isinstance(recorder, Recorder):
        let_the_writer_catch_up(recorder)


def _collect(core: SessionCore, run: IdentificationRun) -> Response:
    """At a tick boundary: detach the run's recorder and reduce its data in a job."""
    if core.loop.recorder is run.recorder:
        core.loop.recorder = None
    log.info("identification trajectory finished", kind=run.kind, t_s=core.t_s())

    def job() -> None:
        try:
            data = finish_run(run, core.description, core.settings.dummy_arm)
            for recorded in (data.dataset_path, data.raw_path):
                record_provenance(core, recorded, data.kind)  # whose data: what validates a model on it
            data.require_signal_map()  # columns that are not what they say are never trained on (issue 27)
        except DarorError as exc:
            core.progress.last_error = f"identification {run.kind}: {exc}"
            refused = isinstance(exc, RecordingSignalMapError)  # written as evidence, refused as data
            log.error(f"identification data {'refused' if refused else 'not saved'}", kind=run.kind, reason=str(exc))
            raise
        finally:
            core.collecting = False
        core.progress.last_identification = {
            "kind": data.kind,
            "dataset": str(data.dataset_path),
            "points": data.points,
            "tracking_rms_mrad": [float(v * 1e3) for v in data.tracking_rms_rad],
            "tracking_max_mrad": [float(v * 1e3) for v in data.tracking_max_rad],
        }

        def saved(supervisor: FsmSupervisor) -> Response:
            supervisor.signals.identification_saved[data.kind] = data.dataset_path
            core.announcements.announce(
                AnnouncementKind.IDENTIFICATION,
                f"identification {data.kind} done: {data.points} stationary points saved to {data.dataset_path}",
                core.t_s(),
            )
            return Response("identification saved", True, supervisor.state_name, detail=data)

        core.supervisor.post("identification saved", saved, essential=True)

    core.jobs.submit(f"save identification {run.kind}", job)
    return Response("identification finished", True, core.supervisor.state_name)


# --- models ------------------------------------------------------------------------------------


def train(core: SessionCore, kind: str | None = None) -> Ticket:
    """Train ``kind`` (default: the session's) on this session's identification data, as a job.

    Returns the request's ticket: resolved at the tick boundary that hands the model over (or
    refuses it), or refused as soon as the job fails (the reason names the error).

    Raises:
        UnknownModelKindError: ``kind`` is not a registered model kind.
        RequestRefusedError: a kind a session does not train, or the training or validation data
            are not saved yet.
    """
    kind = kind or core.settings.model_kind
    kind_entry(kind)  # an unknown kind is refused now, not when the job runs
    trainable = kind_names(lambda entry: entry.session_training)
    if kind not in trainable:
        raise RequestRefusedError(f"a session does not train {kind} models; expected one of {', '.join(trainable)}")
    saved = core.signals.identification_saved
    missing = [k for k in ("training", "validation") if k not in saved]
    if missing:
        raise RequestRefusedError(f"no {' or '.join(missing)} data saved in this session yet: run the protocol first")
    training, validation = saved["training"], saved["validation"]
    origin = validation_origin(core, validation)  # this session's own run
    log.info("request", request=f"train {kind}", origin="operator", training=str(training), validation=str(validation))
    ticket = Ticket(f"train {kind}")

    def job() -> None:
        try:
            trained = train_model(
                kind, training, validation, core.description, core.settings.dummy_arm,
                core.settings.max_validation_rmse_nm, core.session_dir,
            )  # fmt: skip
            post_model(core, trained, f"train {kind}", origin, data={"training_data": str(training)}, ticket=ticket)
        except DarorError as exc:
            core.progress.last_error = f"train {kind}: {exc}"
            _refuse_failed_job(core, ticket, exc)
            raise
        except BaseException as exc:  # a bug: the job's failure is announced; the ticket must not wait forever
            _refuse_failed_job(core, ticket, exc)
            raise

    core.jobs.submit(f"train {kind}", job)
    return ticket


def _refuse_failed_job(core: SessionCore, ticket: Ticket, exc: BaseException) -> None:
    """Resolve a job's ticket as refused because the job failed (from the job's thread; nothing reached the loop)."""
    ticket.resolve(Response(ticket.request, False, core.supervisor.state_name, f"{ticket.request} failed: {exc}"))


def select_model(
    core: SessionCore, path: Path | str, validation: Path | str | None = None, accept_nonconservative: bool = False
) -> Ticket:
    """Use an existing model file once it is validated on held-out data of this pilot (default: this session's validation run).

    Returns the request's ticket: resolved at the tick boundary that makes the model the
    compensation model (or refuses it), or refused as soon as the validation job fails.

    The files are read and checked now (in the caller's thread); the validation and the
    closed-path test run as a job, and the model reaches compensation only if it passes both (a
    model the closed-path test finds not conservative only with ``accept_nonconservative``, the
    operator's explicit confirmation after he saw the energy figure).

    Raises:
        RequestRefusedError: no validation data named and none recorded in this session, or data
            not recorded from this pilot on this robot (:func:`validation_origin`).
        ModelFileError, DataError, NotHeldOutError: a file that cannot be used (named in the message).
    """
    validation_path = (
        Path(validation) if validation is not None else core.signals.identification_saved.get("validation")
    )
    if validation_path is None:
        raise RequestRefusedError(
            "a model is validated on held-out data of this pilot: name a validation file or run the validation "
            "protocol first"
        )
    origin = validation_origin(core, validation_path)
    candidate = read_model_candidate(Path(path), validation_path, core.description)
    log.info(
        "request", request="select model", origin="operator", model=str(path), validation=str(validation_path),
        validation_origin=origin.description, accept_nonconservative=accept_nonconservative,
    )  # fmt: skip

    ticket = Ticket("select model")

    def job() -> None:
        try:
            trained = validate_candidate(candidate, core.settings.max_validation_rmse_nm)
            post_model(core, trained, "select model", origin, accept_nonconservative, ticket=ticket)
        except BaseException as exc:  # the job's failure is announced; the ticket says it too
            _refuse_failed_job(core, ticket, exc)
            raise

    core.jobs.submit("select model", job)
    return ticket


def post_model(
    core: SessionCore,
    trained: TrainedModel,
    request: str,
    origin: ValidationOrigin,
    accept_nonconservative: bool = False,
    data: dict[str, str] | None = None,
    ticket: Ticket | None = None,
) -> None:
    """From a job: hand a validated model to compensation at a tick boundary; refuse one that failed (resolving ``ticket``).

    Refused: a model that failed validation; one the closed-path test finds not conservative,
    unless the operator confirmed it (``accept_nonconservative``). Never while a compensation
    state delivers support (a model swap there is a torque step).
    """
    selected = trained.selected
    closed_path = cvf_models([trained.model])[0].result  # the thesis's test (Table IV), outside the tick
    energy_j = closed_path.steps[-1].energy_j
    summary = {
        "name": selected.name,
        "kind": selected.kind,
        "path": str(selected.path),
        "validation_rmse_nm": trained.validation.rmse_nm,
        "validation_rmse_per_joint_nm": list(trained.validation.rmse_per_joint_nm),
        "validated": selected.validated,
        "max_validation_rmse_nm": selected.max_rmse_nm,
        "validation_data": origin.as_dict(),
        "conservative": closed_path.conservative,
        "closed_path_energy_j": [step.energy_j for step in closed_path.steps],
        "nonconservative_confirmed": accept_nonconservative and not closed_path.conservative,
        "extrapolation": trained.extrapolation.to_dict() if trained.extrapolation is not None else None,
        **(data or {}),
    }

    def apply(supervisor: FsmSupervisor) -> Response:
        reason = None
        if not selected.validated:
            in_use = core.progress.last_model
            reason = (
                f"{selected.name} failed validation: RMSE {trained.validation.rmse_nm:.3g} Nm on held-out data, "
                f"above the session's limit of {selected.max_rmse_nm:g} Nm; it never drives the arm "
                f"(in use: {in_use['name'] if in_use else 'no model'})"
            )
        elif not closed_path.conservative and not accept_nonconservative:
            energies = ", ".join(f"{step.energy_j:.3g}" for step in closed_path.steps)
            reason = (
                f"{selected.name} is not conservative: the closed-path test leaves {energy_j:.3g} J at its finest step "
                f"({energies} J from the coarsest step to the finest: it does not shrink), so along a closed path "
                f"it can put energy into the pilot's arm; to use it anyway, confirm: model {selected.path} "
                f"{origin.path} nonconservative"
            )
        if reason is not None:
            core.progress.last_model_refused = summary
            in_use = core.progress.last_model
            if (
                in_use is not None
                and in_use.get("path") == str(selected.path)
                and supervisor.signals.model is not None
                and supervisor.state.mode != "compensation"
            ):
                # The model in use failed again, on other data of this pilot (a returning pilot's model, approved
                # on his last session's run, then checked on this one's): its approval is withdrawn, or it would
                # reach compensation on data it no longer fits. Not in compensation: that would step the support.
                supervisor.signals.model = None
                core.modes.compensation.model = None
                core.progress.last_model = None
                reason += "; its earlier approval in this session is withdrawn"
                log.warning("model withdrawn", path=str(selected.path), state=supervisor.state_name, t_s=core.t_s())
            core.announcements.announce(AnnouncementKind.MODEL, f"{request}: refused: {reason}", core.t_s())
            return core.refuse(request, reason)
        if supervisor.state.mode == "compensation":
            reason = f"{supervisor.state.name} delivers compensation: change models from another state"
            core.announcements.announce(AnnouncementKind.MODEL, f"{request}: refused: {reason}", core.t_s())
            return core.refuse(request, reason)
        core.modes.compensation.model = trained.model
        core.modes.compensation.damping_nms_per_rad = 0.0  # validated on this pilot's data: transparent
        confirmed = (
            f"; NOT conservative ({energy_j:.3g} J over the closed path), used as the operator confirmed"
            if summary["nonconservative_confirmed"]
            else ""
        )
        core.announcements.announce(
            AnnouncementKind.MODEL,
            f"{request} done: {selected.name} ({selected.kind}) validated, RMSE {trained.validation.rmse_nm:.3g} Nm "
            f"<= {selected.max_rmse_nm:g} Nm on {origin.description}{confirmed}; it is the compensation model now",
            core.t_s(),
        )
        supervisor.signals.model = selected
        core.progress.last_model = {**summary, "approved_by": "validation on held-out data of this pilot"}
        log.info("model in use", **core.progress.last_model, state=supervisor.state_name, t_s=core.t_s())
        return Response(request, True, supervisor.state_name, detail=selected)

    core.supervisor.post(request, apply, essential=True, ticket=ticket)
