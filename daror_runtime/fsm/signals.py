"""What the session has established so far: the facts the FSM's guards read.

A guard never reaches into hardware or files: it reads :class:`SessionSignals`, which the
supervisor updates at tick boundaries only (the latest sample, e-stop tests it observed, the
operator's confirmations, work that finished outside the tick). So a guard's answer cannot
change while a transition is being decided.

Two lifetimes:

* **visit**: e-stop tests and checklist confirmations count only for the visit of the state in
  which they happened. Entering a state (by advance, revert or reset) forgets them, so every
  advance rests on evidence gathered during the current visit.
* **session**: the pilot's ISB limits (forgotten by a reset: the installation is redone), the
  identification data and the selected model (files on disk: kept across resets).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Callable

    from daror_runtime.safety.monitor import SafetyMonitor
    from hal.interface import Sample
    from hal.isb import IsbLimits
    from hal.robot import FloatArray


class EstopButton(StrEnum):
    """The two e-stop inputs, in the order of ``Sample.estop``."""

    OPERATOR = "operator"
    PILOT = "pilot"


ESTOP_BUTTONS: tuple[EstopButton, ...] = (EstopButton.OPERATOR, EstopButton.PILOT)


class Checklist(StrEnum):
    """Checklists the operator confirms at the console (one per state that needs one)."""

    SETTINGS = "settings"  # session settings reviewed: pilot, support level, model, limits
    INSTALLATION = "installation"  # pilot installed: straps, alignment of the shoulder, cables
    SAFETY_EXPERIENCE = "safety_experience"  # the pilot felt the safety limits and knows the e-stop
    A_PRIORI_MODEL = "a_priori_model"  # the A Priori model may support this pilot until a validated one exists


@dataclass(frozen=True)
class SelectedModel:
    """The compensation model chosen for the session and how it did on validation data."""

    name: str
    kind: str
    path: Path | None
    validation_rmse_nm: float | None  # None: not validated
    max_rmse_nm: float

    @property
    def validated(self) -> bool:
        return self.validation_rmse_nm is not None and self.validation_rmse_nm <= self.max_rmse_nm


@dataclass
class SessionSignals:
    """The session's facts, as the guards see them (mutated only at tick boundaries)."""

    monitor: SafetyMonitor | None = None
    sample: Sample | None = None
    at_rest_rad_s: float = 0.05  # every joint slower than this: the robot is at rest
    # visit
    estop_tested: set[EstopButton] = field(default_factory=set)
    confirmed: set[Checklist] = field(default_factory=set)
    # session
    pilot: str | None = None  # the pilot's code (settings or `pilot CODE`); None: nobody named him
    drives_hardware: bool = False  # the backend drives a real robot (a simulated one has its scenario's pilot)
    isb_limits: IsbLimits | None = None
    # the monitor's ISB function for a set of limits (the shoulder's kinematics), and the margin it allows
    isb_angles: Callable[[IsbLimits], Callable[[FloatArray], FloatArray]] | None = None
    isb_margin_rad: float = 0.0
    identification_saved: dict[str, Path] = field(default_factory=dict)  # "training"/"validation" -> dataset file
    model: SelectedModel | None = None
    fault_acknowledged: bool = False
    # a fault's reaction holds or lowers the arm (torque on, under the supervisor's control)
    arm_held: bool = False

    def forget_visit(self) -> None:
        """Entering a state: the previous visit's tests and confirmations no longer count."""
        self.estop_tested.clear()
        self.confirmed.clear()

    def forget_installation(self) -> None:
        """A reset: the pilot's limits are recorded again after the installation is redone."""
        self.forget_visit()
        self.isb_limits = None
