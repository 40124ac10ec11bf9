"""The augmented model in the loop: compensation on the simulated plant with an undeclared effect.

The plant of ``residual_gravity_tilt`` is mounted 2.5 deg off vertical; no model declares it.
A pilot's arm holds the robot at a pose with a stiff, damped spring; whatever torque the arm
supplies is what the compensation model gets wrong. PLF+ fitted on that robot's data leaves
the arm a few tenths of a Nm to carry; the augmented model, with the tilt found and added,
must leave it far less, in lock-step closed loop through the same controllers the session uses.
"""

from __future__ import annotations

import numpy as np
import pytest

from daror_runtime.clocks import LockStepClock
from daror_runtime.control.modes import Compensation
from daror_runtime.control.sea_torque import SeaTorqueController
from daror_runtime.control.sea_torque_design import SeaTorqueDesign
from daror_runtime.loop import ControlLoop, FixedSupervisor
from daror_runtime.models.base import CompensationModel
from daror_runtime.residual.diagnosis import diagnose
from daror_runtime.residual.model import augmented_model
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor
from hal.robot import FloatArray, load_description
from hal.sim.backend import SimHal
from hal.sim.scenario import Scenario, load_scenario
from hal.sim.static_dataset import generate_stationary
from tests.conftest import as_dataset

ARM_STIFFNESS_NM_PER_RAD, ARM_DAMPING_NMS_PER_RAD = 100.0, 5.0


def pilot_torque_rms(
    scenario: Scenario, model: CompensationModel, pose_rad: FloatArray, seconds: float = 3.0
) -> FloatArray:
    """RMS torque (Nm, per joint) the pilot's arm adds to hold ``pose_rad``, after the first second."""
    at_pose = scenario.model_copy(update={"initial_q_deg": [float(v) for v in np.degrees(pose_rad)]})
    hal = SimHal(at_pose)
    hal.open()
    carried: list[FloatArray] = []

    def arm(t_s: float, q: FloatArray, dq: FloatArray) -> FloatArray:
        torque = ARM_STIFFNESS_NM_PER_RAD * (pose_rad - q) - ARM_DAMPING_NMS_PER_RAD * dq
        if t_s >= 1.0:
            carried.append(torque)
        return torque

    hal.set_external_torque(arm)
    controller = Compensation(SeaTorqueController(hal.description.sea, SeaTorqueDesign()), model, 1.0, None)
    controller.reset(hal.read())
    controller.handover.clear()  # full support from the first tick: the stiff arm holds the pose, nothing to hand over
    monitor = SafetyMonitor(SafetyLimits.from_description(hal.description))
    loop = ControlLoop(hal, monitor, FixedSupervisor(controller), LockStepClock(1.0 / hal.rate_hz))  # type: ignore[arg-type]
    loop.run(int(seconds * hal.rate_hz), stop_on_fault=True)
    hal.close()
    assert not monitor.faulted, monitor.latched
    return np.sqrt(np.mean(np.square(carried), axis=0))


@pytest.mark.parametrize("pose_index", [0, 40])
def test_augmented_model_leaves_the_pilot_less_to_carry(pose_index: int) -> None:
    scenario = load_scenario("residual_gravity_tilt")
    description = load_description()
    train = as_dataset(generate_stationary(scenario, "training"))
    diagnosis = diagnose(train, description)
    assert [f.effect.family for f in diagnosis.found] == ["gravity_tilt"]
    base = augmented_model(diagnosis.base_fit)
    augmented = augmented_model(diagnosis.final_fit)
    pose = generate_stationary(scenario, "validation", noise_free=True).q_rad[pose_index]
    truth = scenario.static_plant(description)
    tilted = truth.holding_torque_nm(pose[None, :])[0]
    base_error = float(np.linalg.norm(base.torque(pose) - tilted))
    assert base_error > 0.1, "pick poses where the tilt matters"
    carried_base = pilot_torque_rms(scenario, base, pose)
    carried_augmented = pilot_torque_rms(scenario, augmented, pose)
    # The arm carries what the model gets wrong (to the torque loop's accuracy).
    assert np.linalg.norm(carried_base) == pytest.approx(base_error, rel=0.25)
    assert np.linalg.norm(carried_augmented) < 0.2 * np.linalg.norm(carried_base)
