"""Controllers of the DAROR-01: SEA torque control with a disturbance observer, and the modes on it.

Structure (docs/control.md)::

    MinimalImpedance --(tau_ref = 0)------------------+
    Compensation ----(support x model.torque(q))------+--> SeaTorqueController --> motor torque
    PositionPD ------(K_p e + K_d de + tau_ff)--------+    (C, C_ff, DOB: H_n, Q, alpha)

Every mode is a :class:`~daror_runtime.control.base.Controller`: ``reset(sample)`` when selected,
``update(sample, dt_s) -> Command`` once per tick, no I/O, no threads. The analysis that chose the
observer gain (apparent impedance, passivity) is in :mod:`daror_runtime.control.passivity`; the
position cascade's stability check in :mod:`daror_runtime.control.position`.
"""

from daror_runtime.control.base import ControlDesignError, ControlError, Controller, ControlSettingError
from daror_runtime.control.modes import Compensation, MinimalImpedance, TorqueOff
from daror_runtime.control.position import LinkBounds, PositionPD, design_position_gains, minimum_jerk
from daror_runtime.control.sea_torque import SeaPlant, SeaTorqueController, SeaTorqueDesign

__all__ = [
    "Compensation",
    "ControlDesignError",
    "ControlError",
    "ControlSettingError",
    "Controller",
    "LinkBounds",
    "MinimalImpedance",
    "PositionPD",
    "SeaPlant",
    "SeaTorqueController",
    "SeaTorqueDesign",
    "TorqueOff",
    "design_position_gains",
    "minimum_jerk",
]
