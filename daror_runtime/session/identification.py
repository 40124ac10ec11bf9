"""The identification protocol inside a session (state ``identification``).

The same protocol as ``daror identify`` (:mod:`daror_runtime.identification.protocol`), cut into
the parts a session runs at different times:

* :func:`session_waypoints` (outside the tick): the waypoints of this session: every
  ``waypoint_stride``-th of the file, and only those inside the pilot's recorded ISB limits.
* :func:`prepare_run` (outside the tick, when the operator asks): the trajectory, checked inside the
  pilot's limits, with an approach from where the robot stands; its position controller (stability
  checked); a started recorder. The tick then only switches to it. With ``protocol_file`` or
  ``protocol_budget_s`` the training run is a designed protocol (:func:`designed_training`).
* :func:`finish_run` (a job, after the tick saw the trajectory end): close the recording, reduce
  it to stationary points, write the dataset and the raw log beside it, atomically, and judge their
  signal map from physics (issue 27): a recording whose columns are not what their names say (the
  drives' readings mapped to the wrong joints or signals) is kept as evidence and never trained on.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import structlog

from daror_runtime.data.signal_map import SignalMapError
from daror_runtime.errors import InputError
from daror_runtime.identification.design import DesignSettings, design_protocol
from daror_runtime.identification.protocol import IdentificationRun, finish_recording, plan_run
from daror_runtime.identification.protocol_file import IsbPose, load_protocol
from daror_runtime.identification.settings import IdentificationSettings
from daror_runtime.identification.trajectory import ReferenceTrajectory
from daror_runtime.identification.trajectory_planning import (
    TrajectorySettings,
    build_trajectory,
    build_visit_trajectory,
)
from daror_runtime.identification.waypoints import WaypointSet, load_waypoints
from daror_runtime.models.base import CompensationModel
from hal.isb import AngleRange, IsbLimits, Shoulder
from hal.robot import FloatArray, RobotDescription

log = structlog.get_logger(__name__)

#: Fewer waypoints than this cannot identify PLF+ (and make no useful validation set).
MIN_SESSION_WAYPOINTS = 4


class IdentificationRequestError(InputError):
    """An identification run cannot start (no waypoint inside the pilot's limits, a run already going, ...)."""


class RecordingSignalMapError(SignalMapError):
    """A session's own recording fails the signal-map check: kept as evidence, not used for a model."""


def session_waypoints(
    settings: IdentificationSettings, limits: IsbLimits, description: RobotDescription
) -> tuple[WaypointSet, int]:
    """The waypoints this session visits, and how many of the strided ones lay outside the limits.

    Raises:
        WaypointFileError: the waypoint file is unreadable.
        IdentificationRequestError: fewer than :data:`MIN_SESSION_WAYPOINTS` remain.
    """
    full = load_waypoints(settings.waypoints_file)
    strided = list(range(1, len(full) + 1, settings.waypoint_stride))
    limits = widened(limits, settings.waypoint_tolerance_deg)
    isb = limits.for_box_check(full.isb_rad)
    inside = np.all((isb >= limits.lower_rad) & (isb <= limits.upper_rad), axis=1)
    keep = [n for n in strided if inside[n - 1]]
    if len(keep) < MIN_SESSION_WAYPOINTS:
        raise IdentificationRequestError(
            f"only {len(keep)} of the {len(strided)} waypoints of {full.source} (every "
            f"{settings.waypoint_stride}. one) lie inside the pilot's ISB limits; at least {MIN_SESSION_WAYPOINTS} "
            "are needed: record a wider range of motion or use another waypoint file"
        )
    renumber = {old: new for new, old in enumerate(keep, start=1)}
    training = [renumber[n] for n in full.training_order if n in renumber]
    validation = [renumber[n] for n in full.validation_order if n in renumber]
    if validation == training:
        validation = validation[::-1]
    subset = WaypointSet(
        description=f"{full.description} ({len(keep)} of {len(full)} waypoints for this session)",
        waypoints=[full.waypoints[n - 1] for n in keep],
        training_order=training,
        validation_order=validation,
    )
    return subset, len(strided) - len(keep)


def widened(limits: IsbLimits, tolerance_deg: float) -> IsbLimits:
    """``limits`` with every range widened by ``tolerance_deg`` on both sides (elevation stays >= 0)."""
    if tolerance_deg == 0.0:
        return limits

    def wider(r: AngleRange, floor_deg: float = -180.0) -> AngleRange:
        return AngleRange(
            lower_deg=max(r.lower_deg - tolerance_deg, floor_deg), upper_deg=min(r.upper_deg + tolerance_deg, 180.0)
        )

    return IsbLimits(
        elevation=wider(limits.elevation, 0.0),
        horizontal_rotation=wider(limits.horizontal_rotation),
        axial_rotation=wider(limits.axial_rotation),
        elbow=wider(limits.elbow),
        horizontal_free_below_deg=limits.horizontal_free_below_deg,
    )


def next_free_path(directory: Path, stem: str, suffix: str) -> Path:
    """``directory/stem.suffix``, or ``stem_2.suffix``, ... : a file is never overwritten."""
    # here: data.load brings the table readers along (~25 ms), which a session's start-up does not need
    from daror_runtime.data.load import RAW_LOG_SUFFIX, raw_log_path

    path = directory / f"{stem}{suffix}"
    n = 2
    while path.exists() or raw_log_path(path, RAW_LOG_SUFFIX).exists():
        path = directory / f"{stem}_{n}{suffix}"
        n += 1
    return path


def prepare_run(
    kind: str,
    description: RobotDescription,
    q_now_rad: FloatArray,
    waypoints: WaypointSet,
    limits: IsbLimits,
    settings: IdentificationSettings,
    feedforward: CompensationModel | None,
    dt_s: float,
    directory: Path,
) -> IdentificationRun:
    """The session's run: its trajectory inside the pilot's limits, planned by :func:`plan_run`.

    Raises:
        TrajectoryError: a waypoint or a path leaves the pilot's limits or the device's.
        ControlDesignError: the position gains are unstable for this robot.
    """
    if kind == "training" and (settings.protocol_file is not None or settings.protocol_budget_s is not None):
        trajectory = designed_training(settings, limits, description, q_now_rad, dt_s)
    else:
        trajectory_settings = dataclasses.replace(TrajectorySettings.for_kind(kind), rate_hz=1.0 / dt_s)  # type: ignore[arg-type]
        # Checked against the recorded range widened by the tolerance: still inside what the monitor enforces.
        limits = widened(limits, settings.waypoint_tolerance_deg)
        trajectory = build_trajectory(waypoints, kind, trajectory_settings, limits, description)  # type: ignore[arg-type]
    dataset_path = next_free_path(directory, f"identification_{kind}", ".csv")
    recording = dataset_path.with_name(f".{dataset_path.name}.rec")
    return plan_run(trajectory, description, q_now_rad, settings, feedforward, dt_s, recording, dataset_path)


def designed_training(
    settings: IdentificationSettings,
    limits: IsbLimits,
    description: RobotDescription,
    q_now_rad: FloatArray,
    dt_s: float,
) -> ReferenceTrajectory:
    """The training run as a designed protocol, checked inside the pilot's recorded limits (not widened).

    With ``protocol_file`` the file's protocol; with ``protocol_budget_s`` one designed now for the
    recorded limits, its budget counting the approach from where the robot stands.

    Raises:
        ProtocolFileError: the protocol file is unreadable or wrong.
        DesignError: no protocol within the budget and the limits identifies the model.
        TrajectoryError: the protocol leaves the pilot's limits or the device's.
    """
    if settings.protocol_file is not None:
        protocol, visits = load_protocol(settings.protocol_file)
        return build_visit_trajectory(
            visits, protocol.stops_s, protocol.trajectory_settings(1.0 / dt_s), limits, description
        )
    shoulder = Shoulder.from_description(description)
    start = IsbPose.from_rad(shoulder.isb_from_q(np.asarray(q_now_rad, dtype=float)))
    design = DesignSettings(identification=settings)
    budget = float(settings.protocol_budget_s or 0.0)
    result = design_protocol(budget, limits, description, design, start=start)
    log.info(
        "identification protocol designed",
        budget_s=budget,
        robot_s=round(result.protocol.prediction.robot_time_s, 1),
        poses=result.protocol.prediction.poses,
        stops=result.protocol.prediction.data_stops,
    )
    protocol = result.protocol
    return build_visit_trajectory(
        protocol.waypoint_set(), protocol.stops_s, protocol.trajectory_settings(1.0 / dt_s), limits, description
    )


@dataclasses.dataclass(frozen=True)
class RunSummary:
    """What a finished run left in the session folder."""

    kind: str
    dataset_path: Path
    raw_path: Path  # the raw log beside it (every tick of the run)
    points: int
    tracking_rms_rad: FloatArray
    tracking_max_rad: FloatArray
    #: The signal-map check's failure line (None: the map held): the files are evidence, not training data.
    signal_map_failure: str | None = None

    def require_signal_map(self) -> None:
        """Refuse the run's data for a model if its signal map failed.

        Raises:
            RecordingSignalMapError: one line: the file, the joints and relations that failed, the
                likely mix-up, and that the files are kept but not used.
        """
        if self.signal_map_failure is not None:
            raise RecordingSignalMapError(
                f"{self.signal_map_failure}; kept as evidence, not used for a model: check how the drives' "
                "readings are mapped to the joints (the robot file's node ids, the encoders' signs and PDO mapping)"
            )


def finish_run(run: IdentificationRun, description: RobotDescription, dummy_arm: bool) -> RunSummary:
    """Turn the run's recording into data, write the dataset and raw log atomically, judge their signal map (a job).

    The files are written whatever the signal map's verdict (a recording is evidence); the verdict
    is in :attr:`RunSummary.signal_map_failure`, and :meth:`RunSummary.require_signal_map` refuses
    them for a model. The raw log is judged on every relation (springs, deflection, command,
    velocity, A Priori), the stationary points on the A Priori torque (``dummy_arm``: the Dummy Arm
    is installed); 0.05-0.2 s on a session's run.

    Raises:
        ProtocolAbortedError: no stop of the trajectory held still, or the recorder dropped rows.
        DataError: the recording cannot be read back.
    """
    from daror_runtime.data.load import RAW_LOG_SUFFIX, raw_log_path, write_dataset
    from daror_runtime.data.signal_map import check_raw_log_map, check_stationary_map

    data = finish_recording(run)
    raw_path = raw_log_path(run.dataset_path, RAW_LOG_SUFFIX)
    write_dataset(raw_path, data.raw)
    write_dataset(run.dataset_path, data.stationary)
    run.recorder.path.unlink(missing_ok=True)
    failure = None
    for report in (
        check_raw_log_map(dataclasses.replace(data.raw, source=str(raw_path)), description),
        check_stationary_map(
            dataclasses.replace(data.stationary, source=str(run.dataset_path)), description, dummy_arm
        ),
    ):
        if not report.passed:
            failure = report.failure_line()
            break
    log.info(
        "identification saved",
        kind=run.kind,
        dataset=str(run.dataset_path),
        points=len(data.stationary),
        tracking_rms_mrad=[round(v * 1e3, 2) for v in data.tracking_rms_rad],
        signal_map="consistent" if failure is None else "WRONG",
    )
    return RunSummary(
        run.kind,
        run.dataset_path,
        raw_path,
        len(data.stationary),
        data.tracking_rms_rad,
        data.tracking_max_rad,
        failure,
    )


def abandon_run(run: IdentificationRun, reason: str) -> None:
    """Close an interrupted run's recording and keep it as evidence; no dataset is written (a job)."""
    run.recorder.close()
    log.warning(
        "identification abandoned",
        kind=run.kind,
        reason=reason,
        recording=str(run.recorder.path),
        rows=run.recorder.rows_written,
    )
