"""The mode registry: what a state of ``fsm_spec.yaml`` may let the robot do.

A mode names a kind of behaviour, not a controller object: the runtime builds one controller per
mode when it starts (:mod:`daror_runtime.session.controllers`), and the supervisor switches
between them at tick boundaries. The properties here are what the spec's checks need:

* ``applies_torque``: the mode drives the motors (False only for ``torque_off``). A state's
  torque limit must be 0 exactly when its mode applies no torque.
* ``pilot_driven``: the robot never moves on its own in this mode; only the pilot moves it. The
  e-stop test states (where a fault does not enter FAIL) may only use pilot-driven modes that
  apply torque: there must be torque for the e-stop to remove, and no motion the robot starts.
* ``applies_model``: the mode's torque is a compensation model's. Every transition into a state
  with such a mode must carry a guard that approves the model (validated on the pilot's held-out
  data, or the A Priori model confirmed by the operator): a model nobody approved never drives
  the arm.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ModeInfo:
    name: str
    description: str
    applies_torque: bool
    pilot_driven: bool
    applies_model: bool = False


MODES: dict[str, ModeInfo] = {
    mode.name: mode
    for mode in (
        ModeInfo("torque_off", "drives disabled, no torque", applies_torque=False, pilot_driven=True),
        ModeInfo(
            "minimal_impedance",
            "SEA torque control to zero spring torque: the robot follows the pilot",
            applies_torque=True,
            pilot_driven=True,
        ),
        ModeInfo(
            "hold",
            "position control holding the pose the state was entered in, with gravity feed-forward",
            applies_torque=True,
            pilot_driven=False,
        ),
        ModeInfo(
            "identification",
            "position control along the identification protocol, inside the pilot's ISB limits",
            applies_torque=True,
            pilot_driven=False,
        ),
        ModeInfo(
            "compensation",
            "gravity and stiffness compensation with the selected model at the operator's support level",
            applies_torque=True,
            pilot_driven=True,
            applies_model=True,
        ),
    )
}
