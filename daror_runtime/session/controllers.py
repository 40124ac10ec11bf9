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

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from daror_runtime.control.base import Controller
from daror_runtime.control.modes import Compensation, MinimalImpedance
from daror_runtime.control.motor_position import MotorPositionPD
from daror_runtime.control.position import LinkBounds
from daror_runtime.control.sea_torque import SeaTorqueController
from daror_runtime.control.sea_torque_design import SeaTorqueDesign
from daror_runtime.control.soft_walls import SoftWalls
from daror_runtime.models.base import CompensationModel
from hal.interface import Command, DriveState, Sample
from hal.robot import N_JOINTS, FloatArray, RobotDescription

if TYPE_CHECKING:
    from daror_runtime.identification.protocol import IdentificationRun


class _FixedReference:
    """``t -> (q, 0)``: the pose a :class:`Hold` keeps."""

    def __init__(self) -> None:
        self.q_rad = np.zeros(N_JOINTS)
        self._zero = np.zeros(N_JOINTS)

    def __call__(self, t_s: float) -> tuple[FloatArray, FloatArray]:
        return self.q_rad, self._zero


class _HeldTorque:
    """The feed-forward of a held pose: the torque that held the arm there when the hold began (Nm).

    Behind an enabled drive it is the spring torque of the entry sample, so the hold takes over
    exactly what was carrying the arm (bumpless, and no static error however wrong a model is at
    that pose); behind a disabled drive (torque was off: nothing was held) it is the model's.
    """

    def __init__(self, model: CompensationModel | None, spring_nm_per_rad: float) -> None:
        self.model = model
        self.spring_nm_per_rad = spring_nm_per_rad
        self.value = np.zeros(N_JOINTS)

    def take_over(self, sample: Sample) -> None:
        spring = self.spring_nm_per_rad * (np.asarray(sample.theta_rad, dtype=float) - np.asarray(sample.q_rad))
        fallback = self.model.torque(sample.q_rad) if self.model is not None else np.zeros(N_JOINTS)
        enabled = np.fromiter((d == DriveState.ENABLED for d in sample.drives), dtype=bool, count=N_JOINTS)
        self.value = np.where(enabled, spring, fallback)

    def torque(self, q_rad: FloatArray) -> FloatArray:
        return self.value

    def tick_kernel(self) -> None:
        """No compiled torque: the held value is a constant the controller reads through :meth:`torque`."""
        return None


class Hold:
    """Hold the joint angles of the reset sample (motor position PD; feed-forward: what held the arm there)."""

    def __init__(
        self, description: RobotDescription, feedforward: CompensationModel | None, bounds: LinkBounds, dt_s: float
    ) -> None:
        self._reference = _FixedReference()
        self._held = _HeldTorque(feedforward, description.sea.spring_stiffness_nm_per_rad)
        self.pd = MotorPositionPD(description, self._reference, bounds, feedforward=self._held, dt_s=dt_s)

    def reset(self, sample: Sample) -> None:
        """Hold the sample's pose from now on, with the torque that held it there.

        Raises:
            ControlError: the sample is not finite.
        """
        self._reference.q_rad = np.array(sample.q_rad, dtype=float)
        self._held.take_over(sample)
        self.pd.reset(sample)

    def update(self, sample: Sample, dt_s: float) -> Command:
        return self.pd.update(sample, dt_s)


class IdentificationMode:
    """The mode of state ``identification``: hold, or follow a run's trajectory, then hold again.

    :meth:`start` and :meth:`stop` are called at tick boundaries (by the runtime's requests).
    When a run's trajectory ends, :meth:`update` switches to holding the final pose and leaves the
    run in :attr:`finished_run` for the runtime to collect (outside the tick).
    """

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
    compensation_model: CompensationModel | None,
    dt_s: float,
    support_level: float,
    support_ramp_per_s: float,
    handover_tolerance_nm: float,
    walls: SoftWalls | None = None,
) -> ModeControllers:
    """Every mode's controller for ``description`` at the tick period ``dt_s``.

    ``feedforward`` is the position modes' gravity feed-forward (the A Priori model: it exists
    before anything is identified; a stiff position loop, not the model, holds the arm there);
    ``compensation_model`` is what compensation starts with: None until a model is approved for
    the pilot (compensation refuses to start without one). ``walls``: the soft walls of the
    pilot-driven torque modes (minimal impedance and compensation), configured per state.

    Raises:
        ControlDesignError: a controller design is unstable for this robot.
        ControlSettingError: a support level or ramp out of range.
    """
    bounds = LinkBounds.from_description(description)
    design = SeaTorqueDesign(period_s=dt_s)
    hold = Hold(description, feedforward, bounds, dt_s)
    identification_hold = Hold(description, feedforward, bounds, dt_s)
    controllers = ModeControllers(
        minimal_impedance=MinimalImpedance(SeaTorqueController(description.sea, design), support_ramp_per_s, walls),
        hold=hold,
        identification=IdentificationMode(identification_hold),
        compensation=Compensation(
            SeaTorqueController(description.sea, design),
            compensation_model,
            support_level,
            support_ramp_per_s,
            handover_tolerance_nm,
            walls,
        ),
    )
    _warm_up(controllers, feedforward, dt_s)
    return controllers


def _zeros(readonly: bool) -> FloatArray:
    values = np.zeros(N_JOINTS)
    values.flags.writeable = not readonly
    return values


def _warm_up(controllers: ModeControllers, model: CompensationModel, dt_s: float) -> None:
    """Run every controller once, now, on a still sample, so no compiled kernel loads inside a tick.

    The first call of a cached numba kernel loads it (milliseconds); done in a tick, it made the
    first entry into a torque mode miss three deadlines. Each controller is reset again with the
    real sample when a state selects it, so nothing of this run remains.
    """
    compensation = controllers.compensation
    selected = compensation.model
    compensation.model = model
    try:
        for readonly in (True, False):  # numba compiles per array type: a HAL's read-only arrays and plain ones
            # Springs loaded (theta != q), so the entry handovers run their kernels too.
            theta = _zeros(readonly) + 0.01
            theta.flags.writeable = not readonly
            still = Sample(
                0, 0.0, _zeros(readonly), _zeros(readonly), theta, _zeros(readonly), (False, False),
                (DriveState.ENABLED,) * N_JOINTS,
            )  # fmt: skip
            for controller in (
                controllers.minimal_impedance,
                controllers.hold,
                controllers.identification,
                compensation,
            ):
                controller.reset(still)
                controller.update(still, dt_s)
    finally:
        compensation.model = selected
        controllers.minimal_impedance.handover.clear()
        compensation.handover.clear()
