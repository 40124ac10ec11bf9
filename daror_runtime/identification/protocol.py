"""The identification protocol (thesis Sec. 4.3.1-4.3.2): run a trajectory, keep the stationary points.

One run, on any HAL (the simulated plant in lock-step time, or hardware in real time):

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
stopped automatically (DESIGN.md section 6: an automatic stop that makes the pilot safer).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import structlog

from daror_runtime.clocks import Clock, LockStepClock
from daror_runtime.control.motor_position import DEFAULT_KD_NMS_PER_RAD, DEFAULT_KP_NM_PER_RAD, MotorPositionPD
from daror_runtime.control.position import LinkBounds
from daror_runtime.data.recorder import Recorder, recording_to_raw_log
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.data.stationary import ReductionSettings, reduce_to_stationary
from daror_runtime.errors import DarorError
from daror_runtime.identification.trajectory import ReferenceTrajectory
from daror_runtime.loop import RECORD_COLUMNS, ControlLoop, FixedSupervisor
from daror_runtime.models.base import CompensationModel
from daror_runtime.safety.faults import Fault
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor, faults_text
from hal.interface import Hal
from hal.isb import IsbLimits, Shoulder, monitor_isb_function
from hal.robot import FloatArray

log = structlog.get_logger(__name__)


class ProtocolAbortedError(DarorError):
    """The protocol stopped before its end (a fault); torque is off, nothing was written."""


@dataclass(frozen=True)
class ProtocolSettings:
    """How one identification run is carried out."""

    approach_speed_rad_s: float = 0.25  # mean speed of the joint that moves most on the approach
    min_approach_s: float = 2.0
    settle_s: float = 2.0  # hold at the start pose before the trajectory
    kp_nm_per_rad: float = DEFAULT_KP_NM_PER_RAD
    kd_nms_per_rad: float = DEFAULT_KD_NMS_PER_RAD
    points_per_stop: int = 3  # training: averaged points per stop (validation always one)
    min_samples_per_stop: int = 100  # a stop with fewer stationary samples (0.1 s at 1 kHz) gives no point
    reduction: ReductionSettings = field(default_factory=ReductionSettings)
    progress_every_ticks: int = 1000


@dataclass(frozen=True)
class ProtocolResult:
    """What one run produced, with the figures the closing report needs."""

    kind: str
    stationary: StationaryDataset
    raw: RawLog
    tracking_rms_rad: FloatArray  # (4,) over the trajectory (approach excluded)
    tracking_max_rad: FloatArray  # (4,)
    robot_time_s: float
    wall_time_s: float
    stops: int
    ticks: int
    dropped_rows: int

    @property
    def real_time_factor(self) -> float:
        return self.robot_time_s / self.wall_time_s if self.wall_time_s > 0 else math.inf


def build_position_controller(
    hal: Hal,
    reference: Callable[[float], tuple[FloatArray, FloatArray]],
    settings: ProtocolSettings,
    feedforward: CompensationModel | None = None,
) -> MotorPositionPD:
    """The collocated joint position PD, checked stable for ``hal``'s robot at its tick rate."""
    description = hal.description
    return MotorPositionPD(
        description,
        reference,
        LinkBounds.from_description(description),
        settings.kp_nm_per_rad,
        settings.kd_nms_per_rad,
        feedforward=feedforward,
        dt_s=1.0 / hal.rate_hz,
    )


def run_protocol(
    hal: Hal,
    trajectory: ReferenceTrajectory,
    recording_path: Path,
    isb_limits: IsbLimits | None = None,
    settings: ProtocolSettings | None = None,
    clock: Clock | None = None,
    progress: Callable[[float, float], None] | None = None,
    feedforward: CompensationModel | None = None,
) -> ProtocolResult:
    """Run one identification trajectory on an open ``hal`` and return its data.

    Args:
        hal: an opened backend, drives disabled, the robot at rest.
        trajectory: the training or validation trajectory.
        recording_path: where the tick recording is streamed (must not exist).
        isb_limits: the pilot's ISB limits, enforced every tick (None: device limits only).
        settings: protocol settings.
        clock: default lock-step (virtual time); a real-time clock for hardware.
        progress: called with (robot seconds done, robot seconds total) every
            ``settings.progress_every_ticks`` ticks.
        feedforward: gravity feed-forward of the position PD (typically the A Priori model).

    Raises:
        ProtocolAbortedError: a fault stopped the run (its message says which).
        DarorError: the recording could not be read back or reduced.
    """
    settings = settings or ProtocolSettings()
    description = hal.description
    first = hal.read()
    distance = float(np.abs(trajectory.start_q_rad - first.q_rad).max())
    approach_s = max(distance / settings.approach_speed_rad_s * 1.875, settings.min_approach_s)
    reference = trajectory.with_approach(first.q_rad, approach_s, settings.settle_s)
    controller = build_position_controller(hal, reference, settings, feedforward)
    controller.reset(first)
    limits = SafetyLimits.from_description(description)
    isb_function = None
    if isb_limits is not None:
        isb_function = monitor_isb_function(Shoulder.from_description(description), isb_limits)
        limits = limits.with_isb(isb_limits)
    monitor = SafetyMonitor(limits, isb_angles=isb_function)
    period = 1.0 / hal.rate_hz
    ticks = math.ceil(reference.duration_s / period) + 1
    recorder = Recorder(recording_path, RECORD_COLUMNS)
    recorder.start()
    clock = clock or LockStepClock(period)
    lock_step = isinstance(clock, LockStepClock)
    loop = ControlLoop(hal, monitor, FixedSupervisor(controller), clock, recorder)
    faults: list[Fault] = []
    every = max(settings.progress_every_ticks, 1)
    done = 0
    log.info("identification started", trajectory=trajectory.kind, robot_s=round(reference.duration_s, 1), ticks=ticks)
    wall_start = time.perf_counter()
    try:
        while done < ticks:  # chunks: progress between them, nothing extra inside the tick
            chunk = min(every, ticks - done)
            last = loop.run(chunk, stop_on_fault=True)
            done += chunk
            if last is not None and last.faults:
                faults.extend(last.faults)
                break
            if progress is not None:
                progress(done * period, reference.duration_s)
            if lock_step:  # virtual time may wait for the disk between ticks; real time may not
                let_the_writer_catch_up(recorder)
    finally:
        wall = time.perf_counter() - wall_start
        recorder.close()
    if faults or monitor.faulted:
        message = faults_text(faults or monitor.latched)
        log.error("identification aborted", reason=message)
        raise ProtocolAbortedError(f"identification stopped at t = {hal.read().t_s:.3f} s: {message}")
    if loop.dropped_rows:
        raise ProtocolAbortedError(
            f"the recorder dropped {loop.dropped_rows} rows (the disk could not keep up); the raw log would have "
            "gaps, so no dataset is written"
        )
    raw = recording_to_raw_log(recording_path, drop_nan_rows=True)
    stationary = stationary_points_of_run(raw, reference, settings)
    tracking = tracking_errors(raw, reference)
    log.info(
        "identification finished",
        trajectory=trajectory.kind,
        points=len(stationary),
        wall_s=round(wall, 2),
        real_time_factor=round(reference.duration_s / wall, 1) if wall > 0 else None,
        dropped_rows=loop.dropped_rows,
    )
    return ProtocolResult(
        kind=trajectory.kind,
        stationary=stationary,
        raw=raw,
        tracking_rms_rad=tracking[0],
        tracking_max_rad=tracking[1],
        robot_time_s=loop.clock.ticks * period,
        wall_time_s=wall,
        stops=len(trajectory.stops),
        ticks=loop.clock.ticks,
        dropped_rows=loop.dropped_rows,
    )


def let_the_writer_catch_up(recorder: Recorder, timeout_s: float = 10.0) -> None:
    """Wait (between ticks, lock-step only) until the recorder's backlog is below half its capacity."""
    deadline = time.perf_counter() + timeout_s
    while recorder.rows_accepted - recorder.rows_written > recorder.capacity_rows // 2:
        if recorder.error is not None or time.perf_counter() > deadline:
            return  # the next push raises the latched error, or drops are counted and refused at the end
        time.sleep(0.002)


def stationary_points_of_run(
    raw: RawLog, reference: ReferenceTrajectory, settings: ProtocolSettings
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
    points = reduce_to_stationary(raw, dataclasses.replace(settings.reduction, per_stop="all"))
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
