"""One controller per mode of the FSM, built once when the runtime starts.

Building a controller can take milliseconds (filter design, the stability checks of the position
PD), so it never happens in a transition: the supervisor only switches between these objects and
resets the one it switches to. The modes (:data:`daror_runtime.fsm.modes.MODES`):

* ``torque_off``: None (the loop writes torque off).
* ``minimal_impedance``: :class:`~daror_runtime.control.modes.MinimalImpedance`.
* ``hold``: :class:`Hold`, the collocated motor position PD holding the pose of its reset.
* ``identification``: :class:`IdentificationMode`: holds until the operator starts a run, follows
  the run's trajectory, and holds the final pose when it ends.
* ``compensation``: :class:`~daror_runtime.control.modes.Compensation` with the session's model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from daror_runtime.control.base import Controller
from daror_runtime.control.modes import Compensation, MinimalImpedance
from daror_runtime.control.motor_position import MotorPositionPD
from daror_runtime.control.position import LinkBounds
from daror_runtime.control.sea_torque import SeaTorqueController, SeaTorqueDesign
from daror_runtime.models.base import CompensationModel
from hal.interface import Command, Sample
from hal.robot import N_JOINTS, FloatArray, RobotDescription

if TYPE_CHECKING:
    from daror_runtime.data.recorder import Recorder
    from daror_runtime.identification.protocol import ProtocolSettings
    from daror_runtime.identification.trajectory import ReferenceTrajectory


class _FixedReference:
    """``t -> (q, 0)``: the pose a :class:`Hold` keeps."""

    def __init__(self) -> None:
        self.q_rad = np.zeros(N_JOINTS)
        self._zero = np.zeros(N_JOINTS)

    def __call__(self, t_s: float) -> tuple[FloatArray, FloatArray]:
        return self.q_rad, self._zero


class Hold:
    """Hold the joint angles of the reset sample (motor position PD with gravity feed-forward)."""

    commands: tuple[str, ...] = ("motor_torque",)

    def __init__(
        self, description: RobotDescription, feedforward: CompensationModel | None, bounds: LinkBounds, dt_s: float
    ) -> None:
        self._reference = _FixedReference()
        self.pd = MotorPositionPD(description, self._reference, bounds, feedforward=feedforward, dt_s=dt_s)

    @property
    def target_q_rad(self) -> FloatArray:
        return self._reference.q_rad

    def reset(self, sample: Sample) -> None:
        """Hold the sample's pose from now on.

        Raises:
            ControlError: the sample is not finite.
        """
        self._reference.q_rad = np.array(sample.q_rad, dtype=float)
        self.pd.reset(sample)

    def update(self, sample: Sample, dt_s: float) -> Command:
        return self.pd.update(sample, dt_s)


@dataclass
class IdentificationRun:
    """One protocol run, prepared outside the tick and handed to :class:`IdentificationMode`."""

    kind: str  # "training" or "validation"
    reference: ReferenceTrajectory  # approach + trajectory, t = 0 at the start sample
    controller: MotorPositionPD
    recorder: Recorder
    dataset_path: Path
    protocol: ProtocolSettings
    t0_s: float = 0.0
    end_t_s: float = field(default=float("inf"))

    @property
    def duration_s(self) -> float:
        return self.reference.duration_s


class IdentificationMode:
    """The mode of state ``identification``: hold, or follow a run's trajectory, then hold again.

    :meth:`start` and :meth:`stop` are called at tick boundaries (by the runtime's requests).
    When a run's trajectory ends, :meth:`update` switches to holding the final pose and leaves the
    run in :attr:`finished_run` for the runtime to collect (outside the tick).
    """

    commands: tuple[str, ...] = ("motor_torque",)

    def __init__(self, hold: Hold) -> None:
        self.hold = hold
        self._active: Controller = hold
        self.run: IdentificationRun | None = None
        self.finished_run: IdentificationRun | None = None

    @property
    def running(self) -> bool:
        return self.run is not None

    def reset(self, sample: Sample) -> None:
        """Entering the state (or torque returning): hold here; a run in progress is not resumed."""
        self.run = None
        self._active = self.hold
        self.hold.reset(sample)

    def start(self, run: IdentificationRun, sample: Sample) -> None:
        """Follow ``run`` from this sample on.

        Raises:
            ControlError: the run's reference does not start at the robot's pose.
        """
        run.controller.reset(sample)
        run.t0_s = sample.t_s
        run.end_t_s = sample.t_s + run.duration_s
        self.run = run
        self._active = run.controller

    def stop(self, sample: Sample) -> IdentificationRun | None:
        """Abandon the run (if any) and hold the present pose; returns the abandoned run."""
        run, self.run = self.run, None
        self._active = self.hold
        self.hold.reset(sample)
        return run

    def update(self, sample: Sample, dt_s: float) -> Command:
        run = self.run
        if run is not None and sample.t_s >= run.end_t_s:
            self.run = None
            self.finished_run = run
            self._active = self.hold
            self.hold.reset(sample)
        return self._active.update(sample, dt_s)


@dataclass
class ModeControllers:
    """The controllers of a session, by mode."""

    minimal_impedance: MinimalImpedance
    hold: Hold
    identification: IdentificationMode
    compensation: Compensation

    def by_mode(self) -> dict[str, Controller | None]:
        return {
            "torque_off": None,
            "minimal_impedance": self.minimal_impedance,
            "hold": self.hold,
            "identification": self.identification,
            "compensation": self.compensation,
        }


def build_mode_controllers(
    description: RobotDescription,
    feedforward: CompensationModel,
    compensation_model: CompensationModel,
    dt_s: float,
    support_level: float,
    support_ramp_per_s: float,
) -> ModeControllers:
    """Every mode's controller for ``description`` at the tick period ``dt_s``.

    ``feedforward`` is the position modes' gravity feed-forward (the A Priori model: it exists
    before anything is identified); ``compensation_model`` is what compensation starts with.

    Raises:
        ControlDesignError: a controller design is unstable for this robot.
        ControlSettingError: a support level or ramp out of range.
    """
    bounds = LinkBounds.from_description(description)
    design = SeaTorqueDesign(period_s=dt_s)
    hold = Hold(description, feedforward, bounds, dt_s)
    identification_hold = Hold(description, feedforward, bounds, dt_s)
    return ModeControllers(
        minimal_impedance=MinimalImpedance(SeaTorqueController(description.sea, design)),
        hold=hold,
        identification=IdentificationMode(identification_hold),
        compensation=Compensation(
            SeaTorqueController(description.sea, design), compensation_model, support_level, support_ramp_per_s
        ),
    )
