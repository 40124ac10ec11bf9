"""Controllers of the DAROR-01: SEA torque control with a disturbance observer, and the modes on it.

Structure (docs/control.md)::

    MinimalImpedance --(tau_ref = 0)------------------+
    Compensation ----(support x model.torque(q))------+--> SeaTorqueController --> motor torque
                                                           (C, C_ff, DOB: H_n, Q, alpha)
    MotorPositionPD -(K_p (theta_ref - theta) + K_d (dq_ref - theta') + tau_ff)--> motor torque

Every mode is a :class:`~daror_runtime.control.base.Controller`: ``reset(sample)`` when selected,
``update(sample, dt_s) -> Command`` once per tick, no I/O, no threads (``tests/test_boundaries.py``
checks the I/O). What runs in the tick and what is designed once before the loop live apart:

* in the tick: :mod:`.sea_torque` (the torque loop's state and compiled kernel), :mod:`.modes`,
  :mod:`.handover`, :mod:`.motor_position` (the identification's position PD);
* before the loop: :mod:`.sea_torque_design` (gains, filters and observer of the torque loop),
  :mod:`.filters` (transfer functions, discretised once; their state-space matrices are what the
  kernels run), :mod:`.position` (the link bounds position gains are checked over), and
  :mod:`.passivity` (the analysis that chose the observer gain: apparent impedance, passivity).

The names below are imported when first asked for (PEP 562), not with the package: importing
one module (``daror_runtime.control.motor_position``, all ``daror identify`` needs) then does not
load the torque loop's kernel, its filter design and ``scipy.signal`` (~0.7 s and ~75 MB).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from daror_runtime.control.base import ControlDesignError, ControlError, Controller, ControlSettingError

if TYPE_CHECKING:
    from daror_runtime.control.modes import Compensation, MinimalImpedance, TorqueOff
    from daror_runtime.control.position import LinkBounds
    from daror_runtime.control.sea_torque import SeaTorqueController
    from daror_runtime.control.sea_torque_design import SeaPlant, SeaTorqueDesign


def __getattr__(name: str) -> object:
    """The package's names of the heavier modules, imported at first use."""
    if name in ("Compensation", "MinimalImpedance", "TorqueOff"):
        from daror_runtime.control import modes

        return getattr(modes, name)
    if name == "LinkBounds":
        from daror_runtime.control.position import LinkBounds

        return LinkBounds
    if name == "SeaTorqueController":
        from daror_runtime.control.sea_torque import SeaTorqueController

        return SeaTorqueController
    if name in ("SeaPlant", "SeaTorqueDesign"):
        from daror_runtime.control import sea_torque_design

        return getattr(sea_torque_design, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "Compensation",
    "ControlDesignError",
    "ControlError",
    "ControlSettingError",
    "Controller",
    "LinkBounds",
    "MinimalImpedance",
    "SeaPlant",
    "SeaTorqueController",
    "SeaTorqueDesign",
    "TorqueOff",
]
