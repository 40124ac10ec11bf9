"""The identification protocol's trajectories (thesis Sec. 4.3.1-4.3.2).

:mod:`.waypoints` reads and validates the ISB waypoint set (``waypoints.yaml`` ships with the
package); :mod:`.trajectory` turns it into the checked training and validation references the
position controller samples once per tick.
"""

from daror_runtime.identification.trajectory import (
    ReferenceTrajectory,
    Stop,
    TrajectoryError,
    TrajectoryKind,
    TrajectorySettings,
    build_trajectory,
)
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
