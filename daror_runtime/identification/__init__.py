"""The identification protocol's trajectories (thesis Sec. 4.3.1-4.3.2).

:mod:`.waypoints` reads and validates the ISB waypoint set (``waypoints.yaml`` ships with the
package); :mod:`.trajectory_planning` turns it into the checked training and validation
trajectories before anything moves; :mod:`.trajectory` holds the built
:class:`~daror_runtime.identification.trajectory.ReferenceTrajectory` the position controller
samples once per tick.
"""

from daror_runtime.identification.trajectory import ReferenceTrajectory, Stop, TrajectoryKind
from daror_runtime.identification.trajectory_planning import TrajectoryError, TrajectorySettings, build_trajectory
from daror_runtime.identification.waypoints import Waypoint, WaypointFileError, WaypointSet, load_waypoints

__all__ = [
    "ReferenceTrajectory",
    "Stop",
    "TrajectoryError",
    "TrajectoryKind",
    "TrajectorySettings",
    "Waypoint",
    "WaypointFileError",
    "WaypointSet",
    "build_trajectory",
    "load_waypoints",
]
