"""The identification protocol (thesis Sec. 4.3.1-4.3.2): run a trajectory, keep the stationary points.

One pipeline, two callers. A session runs it in the FSM's state ``identification``
(:mod:`daror_runtime.session.identification`, on any backend); ``daror identify`` runs it on the
simulated plant alone (:func:`run_protocol`, no FSM, so never on hardware). Both plan a run with
:func:`plan_run` and turn its recording into data with :func:`finish_recording`:

1. *Approach*: from wherever the robot stands, a minimum-jerk joint move to the trajectory's
   start pose, then a short hold so the arm settles.
2. *Trajectory*: a joint position PD on each motor angle (collocated, Kp = 700 Nm/rad as in the
   thesis's Sec. 2.2.4; ``daror_runtime.control.motor_position``), with the reference velocity
   and a gravity feed-forward model (the A Priori model: it exists before anything is
   identified), tracks the training or validation trajectory, while the recorder streams every
   tick to disk.
3. *Data*: the recording becomes the raw log; the raw log is reduced to stationary points
   (Butterworth on velocity, threshold, Sec. 4.3.2, ``daror_runtime.data.stationary``), and only
   points inside the trajectory's own stops are kept (the approach is not data). Training keeps
   ``points_per_stop`` averaged points per stop; validation one point per waypoint stop.

Safety: the run stops on the first fault (torque is already off: the safety filter did that in
the same tick) and :class:`ProtocolAbortedError` names the fault. The pilot's ISB limits, when
given, are enforced every tick by the safety monitor, so a trajectory that would leave them is
stopped automatically (an automatic stop that makes the pilot safer, docs/safety.md). A robot that
starts outside them enters them on the approach (checked before it moves; D135).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import structlog

from daror_runtime.clocks import LockStepClock
from daror_runtime.control.motor_position import MotorPositionPD
from daror_runtime.control.position import LinkBounds
from daror_runtime.data.recorder import Recorder
from daror_runtime.data.recording_reader import recording_to_raw_log
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.data.stationary import ReductionSettings, reduce_to_stationary
from daror_runtime.data.tick_row import RECORD_COLUMNS
from daror_runtime.errors import DarorError, UsageError
from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.identification.trajectory import ReferenceTrajectory
from daror_runtime.identification.trajectory_planning import check_approach, prepend_approach
from daror_runtime.loop import ControlLoop, FixedSupervisor, TickResult
from daror_runtime.models.base import CompensationModel
from daror_runtime.safety.faults import Fault
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor, faults_text
from hal.interface import Hal
from hal.isb import IsbLimits, Shoulder, monitor_isb_function
from hal.robot import FloatArray, RobotDescription

log = structlog.get_logger(__name__)


class ProtocolAbortedError(DarorError):
    """The protocol stopped before its end (a fault); torque is off, nothing was written."""


@dataclass
class IdentificationRun:
    """One protocol run, planned outside the tick: what the tick follows and where it records.

    The session hands it to its identification mode; ``daror identify`` runs it in a loop of its
    own. Both finish it with :func:`finish_recording`.
    """

    kind: str  # "training" or "validation"
    reference: ReferenceTrajectory  # approach + trajectory, t = 0 at the start sample
    controller: MotorPositionPD
    recorder: Recorder
    settings: IdentificationSettings
    dataset_path: Path  # where the caller writes the stationary dataset (the raw log beside it)
    t0_s: float = 0.0
    end_t_s: float = field(default=float("inf"))

    @property
    def duration_s(self) -> float:
        return self.reference.duration_s


@dataclass(frozen=True)
class RunData:
    """What a finished run's recording holds: the raw log, its stationary points, the tracking errors."""

    raw: RawLog
    stationary: StationaryDataset
    tracking_rms_rad: FloatArray  # (4,) over the trajectory (approach excluded)
    tracking_max_rad: FloatArray  # (4,)


@dataclass(frozen=True)
class ProtocolResult:
    """What one ``daror identify`` run produced, with the figures the closing report needs."""

    kind: str
    data: RunData
    robot_time_s: float
    wall_time_s: float
    stops: int
    ticks: int
    dropped_rows: int  # rows the recorder could not take (a run that dropped any is refused)

    @property
    def stationary(self) -> StationaryDataset:
        return self.data.stationary

    @property
    def raw(self) -> RawLog:
        return self.data.raw

    @property
    def tracking_rms_rad(self) -> FloatArray:
        return self.data.tracking_rms_rad

    @property
    def tracking_max_rad(self) -> FloatArray:
        return self.data.tracking_max_rad

    @property
    def real_time_factor(self) -> float:
        return self.robot_time_s / self.wall_time_s if self.wall_time_s > 0 else math.inf


def plan_run(
    trajectory: ReferenceTrajectory,
    description: RobotDescription,
    q_now_rad: FloatArray,
    settings: IdentificationSettings,
    feedforward: CompensationModel | None,
    dt_s: float,
    recording_path: Path,
    dataset_path: Path,
) -> IdentificationRun:
    """Everything a run needs, built outside the tick; the recorder is started (its file exists).

    The reference is the trajectory preceded by a minimum-jerk approach from ``q_now_rad`` (rad)
    and a hold of ``settings.settle_s``; the collocated motor position PD tracks it with the
    gravity ``feedforward`` (typically the A Priori model).

    Raises:
        ControlDesignError: the position gains are unstable for this robot at ``dt_s``.
        RecorderError: the recording file cannot be created.
    """
    q_now = np.asarray(q_now_rad, dtype=float)
    distance = float(np.abs(trajectory.start_q_rad - q_now).max())
    approach_s = settings.approach_duration_s(distance)
    reference = prepend_approach(trajectory, q_now, approach_s, settings.settle_s)
    controller = MotorPositionPD(
        description,
        reference,
        LinkBounds.from_description(description),
        settings.kp_nm_per_rad,
        settings.kd_nms_per_rad,
        feedforward=feedforward,
        dt_s=dt_s,
    )
    recorder = Recorder(recording_path, RECORD_COLUMNS)
    recorder.start()
    log.info(
        "identification planned",
        kind=trajectory.kind,
        robot_s=round(reference.duration_s, 1),
        approach_s=round(approach_s, 1),
        recording=str(recording_path),
    )
    return IdentificationRun(trajectory.kind, reference, controller, recorder, settings, dataset_path)


def finish_recording(run: IdentificationRun) -> RunData:
    """Close the run's recording and turn it into data (outside the tick; the recording is kept).

    Raises:
        ProtocolAbortedError: the recorder dropped rows (the raw log would have gaps), or no
            stop of the trajectory held still.
        DataError: the recording cannot be read back.
    """
    run.recorder.close()
    recording = run.recorder.path
    if run.recorder.dropped_rows:
        raise ProtocolAbortedError(
            f"{recording}: the recorder dropped {run.recorder.dropped_rows} rows (the disk could not keep up); "
            "the raw log would have gaps, so no dataset is written"
        )
    raw = recording_to_raw_log(recording, drop_nan_rows=True)
    stationary = stationary_points_of_run(raw, run.reference, run.settings)
    rms, worst = tracking_errors(raw, run.reference)
    return RunData(raw, stationary, rms, worst)


def run_protocol(
    hal: Hal,
    trajectory: ReferenceTrajectory,
    recording_path: Path,
    dataset_path: Path,
    isb_limits: IsbLimits | None = None,
    settings: IdentificationSettings | None = None,
    progress: Callable[[float, float], None] | None = None,
    feedforward: CompensationModel | None = None,
    progress_every_ticks: int = 1000,
) -> ProtocolResult:
    """Run one identification trajectory on an open simulated ``hal``, in lock-step, and return its data.

    The run is planned and finished by the same pieces a session uses (:func:`plan_run`,
    :func:`finish_recording`), but its loop has no FSM: no e-stop tests, no pilot installation,
    no operator. It therefore runs only on a backend on virtual time (a simulation); on hardware,
    identification runs inside a session, in the FSM's state ``identification``.

    Args:
        hal: an opened backend on virtual time, drives disabled, the robot at rest.
        trajectory: the training or validation trajectory.
        recording_path: where the tick recording is streamed (must not exist; kept afterwards).
        dataset_path: where the caller will write the stationary dataset (not written here).
        isb_limits: the pilot's ISB limits, enforced every tick (None: device limits only). A robot
            that starts outside them (its home pose below the pilot's lowest elevation) enters them
            on the approach, held meanwhile to no further out than its start (:func:`check_approach`);
            from the tick the arm is inside, or at the latest when the approach and settle hold end,
            they are enforced.
        settings: how the run is carried out (default :class:`IdentificationSettings`).
        progress: called with (robot seconds done, robot seconds total) every
            ``progress_every_ticks`` ticks.
        feedforward: gravity feed-forward of the position PD (typically the A Priori model).

    Raises:
        UsageError: ``hal`` drives hardware (not on virtual time).
        TrajectoryError: the approach from where the robot stands would leave the pilot's limits
            once inside them, or stray further out on its way in (before anything moved).
        ProtocolAbortedError: a fault stopped the run (its message says which), or its recording
            is unusable.
        DarorError: the recording could not be read back or reduced.
    """
    if not hal.virtual_time:
        raise UsageError(
            f"the {hal.kind} backend drives hardware: an identification run outside a session skips the FSM "
            "(e-stop tests, installation, operator); expected a simulated backend, or identify in a session "
            "(daror console, state identification)"
        )
    settings = settings or IdentificationSettings()
    description = hal.description
    period = 1.0 / hal.rate_hz
    first = hal.read()
    shoulder = Shoulder.from_description(description)
    approach = None
    if isb_limits is not None:  # before anything is planned or recorded: a refusal leaves nothing behind
        approach = check_approach(
            shoulder, isb_limits, first.q_rad, trajectory.start_q_rad, "the approach from where the robot stands"
        )
    run = plan_run(trajectory, description, first.q_rad, settings, feedforward, period, recording_path, dataset_path)
    run.controller.reset(first)
    device = SafetyLimits.from_description(description)
    limits, isb_function = device, None
    if approach is not None:
        # The arm may start outside the pilot's limits (a pilot who cannot reach the robot's home pose):
        # until it has entered them it is held to the approach's own limits, no further out than its start.
        limits = device.with_isb(approach.on_the_way)
        isb_function = monitor_isb_function(shoulder, approach.on_the_way)
    monitor = SafetyMonitor(limits, isb_angles=isb_function)
    reference = run.reference
    ticks = math.ceil(reference.duration_s / period) + 1
    loop = ControlLoop(hal, monitor, FixedSupervisor(run.controller), LockStepClock(period), run.recorder)
    faults: list[Fault] = []
    every = max(progress_every_ticks, 1)
    done = 0
    log.info("identification started", trajectory=trajectory.kind, robot_s=round(reference.duration_s, 1), ticks=ticks)
    wall_start = time.perf_counter()
    try:
        if approach is not None and isb_limits is not None and not approach.starts_inside:
            done = _enter_the_limits(loop, monitor, shoulder, isb_limits, math.ceil(reference.time_offset_s / period))
            faults.extend(monitor.latched)
        while done < ticks and not faults:  # chunks: progress between them, nothing extra inside the tick
            chunk = min(every, ticks - done)
            last = loop.run(chunk, stop_on_fault=True)
            done += chunk
            if last is not None and last.faults:
                faults.extend(last.faults)
                break
            if progress is not None:
                progress(done * period, reference.duration_s)
            let_the_writer_catch_up(run.recorder)  # virtual time may wait for the disk between ticks
    finally:
        wall = time.perf_counter() - wall_start
        run.recorder.close()
    if faults or monitor.faulted:
        message = faults_text(faults or monitor.latched)
        log.error("identification aborted", reason=message)
        raise ProtocolAbortedError(f"identification stopped at t = {hal.read().t_s:.3f} s: {message}")
    data = finish_recording(run)
    log.info(
        "identification finished",
        trajectory=trajectory.kind,
        points=len(data.stationary),
        wall_s=round(wall, 2),
        real_time_factor=round(reference.duration_s / wall, 1) if wall > 0 else None,
    )
    return ProtocolResult(
        kind=trajectory.kind,
        data=data,
        robot_time_s=loop.clock.ticks * period,
        wall_time_s=wall,
        stops=len(trajectory.stops),
        ticks=loop.clock.ticks,
        dropped_rows=loop.dropped_rows,
    )


def _enter_the_limits(
    loop: ControlLoop, monitor: SafetyMonitor, shoulder: Shoulder, isb_limits: IsbLimits, deadline_ticks: int
) -> int:
    """Tick until the measured arm is inside the pilot's ISB limits, then enforce them; the ticks run.

    Before that the monitor holds the arm to the approach's limits (:func:`check_approach`). At
    ``deadline_ticks`` (the end of the approach and the settle hold) the pilot's limits are enforced
    whether or not the arm entered them: an arm still outside then faults at the next tick.
    """
    angles = monitor_isb_function(shoulder, isb_limits)
    lower, upper = isb_limits.lower_rad, isb_limits.upper_rad

    def entered(result: TickResult) -> bool:
        sample = result.sample
        if sample is None:
            return False
        isb = angles(sample.q_rad)
        return bool(np.all((isb >= lower) & (isb <= upper)))

    last = loop.run(max(deadline_ticks, 1), stop=entered, stop_on_fault=True)
    monitor.set_limits(
        monitor.limits.with_isb(isb_limits), monitor_isb_function(shoulder, isb_limits)
    )  # from the next tick on
    if last is not None and last.sample is not None:
        log.info("the arm entered the pilot's ISB limits", t_s=round(last.sample.t_s, 3), inside=entered(last))
    return loop.clock.ticks


def let_the_writer_catch_up(recorder: Recorder, timeout_s: float = 10.0) -> None:
    """Wait (between ticks, lock-step only) until the recorder's backlog is below half its capacity."""
    deadline = time.perf_counter() + timeout_s
    while recorder.rows_accepted - recorder.rows_written > recorder.capacity_rows // 2:
        if recorder.error is not None or time.perf_counter() > deadline:
            return  # the next push raises the latched error, or drops are counted and refused at the end
        time.sleep(0.002)


def stationary_points_of_run(
    raw: RawLog, reference: ReferenceTrajectory, settings: IdentificationSettings
) -> StationaryDataset:
    """Points of the trajectory's stops: the raw log's stationary samples inside each stop's window.

    Stationary is decided the thesis's way (filtered velocity below a threshold, Sec. 4.3.2, by
    :func:`reduce_to_stationary`, which also gives ``dir``); *which* stop a sample belongs to
    comes from the trajectory, which knows when the robot was told to stand still. Each stop's
    samples are split into ``points_per_stop`` consecutive parts (training) or kept as one
    (validation: one point per waypoint stop) and averaged. A stop with fewer than
    ``min_samples_per_stop`` stationary samples is left out.
    """
    per_stop = settings.points_per_stop if reference.kind == "training" else 1
    points = reduce_to_stationary(raw, ReductionSettings(per_stop="all"))
    t = points.t_s if points.t_s is not None else np.zeros(len(points))
    direction = points.direction if points.direction is not None else np.zeros_like(points.q_rad)
    stops = reference.stops if reference.kind == "training" else reference.waypoint_stops
    t0 = raw.t_s[0]  # the reference's clock started with the first recorded tick
    starts = np.searchsorted(t, [s.start_s + t0 for s in stops], side="left")
    ends = np.searchsorted(t, [s.end_s + t0 for s in stops], side="right")
    q, tau, d, times = [], [], [], []
    for first, last in zip(starts, ends, strict=True):
        if last - first < settings.min_samples_per_stop:
            continue
        for part in np.array_split(np.arange(first, last), per_stop):
            q.append(points.q_rad[part].mean(axis=0))
            tau.append(points.tau_nm[part].mean(axis=0))
            d.append(direction[part[-1]])
            times.append(t[part].mean())
    if not q:
        raise ProtocolAbortedError(f"{raw.source}: no stop of the trajectory held still; no stationary point")
    return StationaryDataset(np.array(q), np.array(tau), np.array(d), np.array(times), points.source)


def tracking_errors(raw: RawLog, reference: ReferenceTrajectory) -> tuple[FloatArray, FloatArray]:
    """RMS and maximum of ``q_ref - q`` per joint over the trajectory (after approach and settling)."""
    elapsed = raw.t_s - raw.t_s[0]
    first = int(np.searchsorted(elapsed, reference.time_offset_s))
    squares, worst = np.zeros(4), np.zeros(4)
    for start in range(first, len(elapsed), 50_000):  # chunks: sampling the reference gathers pieces
        stop = min(start + 50_000, len(elapsed))
        q_ref, _ = reference.sample(elapsed[start:stop])
        error = q_ref - raw.q_rad[start:stop]
        squares += np.sum(error**2, axis=0)
        worst = np.maximum(worst, np.abs(error).max(axis=0))
    count = max(len(elapsed) - first, 1)
    return np.sqrt(squares / count), worst
