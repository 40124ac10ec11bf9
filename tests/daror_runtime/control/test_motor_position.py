"""The collocated joint position PD on the motor angle (the identification's position controller)."""

from __future__ import annotations

import numpy as np
import pytest

from daror_runtime.clocks import LockStepClock
from daror_runtime.control.base import ControlDesignError, ControlError
from daror_runtime.control.motor_position import MotorPositionPD, _motor_pd, motor_loop_spectral_radius
from daror_runtime.control.position import LinkBounds
from daror_runtime.identification.trajectory_planning import build_trajectory
from daror_runtime.identification.waypoints import WaypointSet, load_waypoints
from daror_runtime.loop import ControlLoop, FixedSupervisor
from daror_runtime.models.base import CompensationModel, TickKernel
from daror_runtime.models.linear import APModel
from daror_runtime.safety.limits import SafetyLimits
from daror_runtime.safety.monitor import SafetyMonitor
from hal.interface import Command
from hal.robot import RobotDescription
from hal.sim.backend import SimHal

BOUNDS: dict[str, LinkBounds] = {}


def bounds(description: RobotDescription) -> LinkBounds:
    if "b" not in BOUNDS:
        BOUNDS["b"] = LinkBounds.from_description(description)
    return BOUNDS["b"]


def hold(hal: SimHal, kp: float, kd: float, seconds: float = 2.0, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The control law itself (the compiled kernel) with the given gains, unchecked, holding the start
    pose shifted by ``offset`` rad on every joint; returns the motor torques and link angles per tick."""
    hal.open()
    first = hal.read()
    target = first.q_rad + offset
    sea = hal.description.sea
    alpha = 1.0 - np.exp(-2.0 * np.pi * 50.0 * 1e-3)
    gains = np.vstack([np.full(4, kp), np.full(4, kd), np.full(4, 1.0 / sea.spring_stiffness_nm_per_rad),
                       np.full(4, alpha), np.full(4, 1e3), np.full(4, sea.max_motor_torque_nm)])  # fmt: skip
    state = np.vstack([first.theta_rad, np.zeros(4)])
    torques, angles = [], []
    for _ in range(int(seconds * 1000)):
        sample = hal.read()
        out = np.empty(4)
        _motor_pd(target, np.zeros(4), np.zeros(4), sample.theta_rad, state, gains, out)
        torques.append(out)
        angles.append(sample.q_rad)
        hal.write(Command(out, True))
    return np.array(torques), np.array(angles)


def test_default_gains_pass_the_design_check(description: RobotDescription) -> None:
    controller = MotorPositionPD(description, lambda t: (np.zeros(4), np.zeros(4)), bounds(description))
    assert controller.kp_nm_per_rad.tolist() == [700.0] * 4  # the thesis's K_p (Sec. 2.2.4)
    assert np.all(controller.spectral_radius < np.exp(-1e-3 / 2.0))


def test_the_analysis_refuses_what_the_plant_shows_unstable(description: RobotDescription) -> None:
    """K_d = 400 Nms/rad: the motor's velocity loop (one tick late) overcorrects. The analysis says
    so, and the full plant, held with these gains, rings up to the saturation."""
    with pytest.raises(ControlDesignError, match=r"joint 1: .* is unstable"):
        MotorPositionPD(description, lambda t: (np.zeros(4), np.zeros(4)), bounds(description), 700.0, 400.0)
    radius = motor_loop_spectral_radius(700.0, 400.0, 0.25, 0.0, 289.0, 0.05, 0.0, 50.0, 1e-3, 1, 0.05)
    assert radius > 1.0
    unstable, _ = hold(SimHal("exo_dummy_arm"), 700.0, 400.0, seconds=1.0)
    stable, _ = hold(SimHal("exo_dummy_arm"), 700.0, 20.0, seconds=1.0)
    assert np.abs(unstable[-200:]).max() > 30.0  # near the 40 Nm saturation
    assert np.std(stable[-500:], axis=0).max() < 1.0


def test_the_thesis_derivative_gain_is_stable_but_noisy() -> None:
    """Why K_d = 20 and not the thesis's 175: quantisation noise of the 1e-4 rad encoder."""
    thesis, _ = hold(SimHal("exo_dummy_arm"), 700.0, 175.0)
    ours, _ = hold(SimHal("exo_dummy_arm"), 700.0, 20.0)
    noise_thesis = np.std(thesis[-1000:], axis=0).max()
    noise_ours = np.std(ours[-1000:], axis=0).max()
    assert noise_thesis > 10.0  # Nm RMS of motor torque at a standstill
    assert noise_ours < 1.0


def test_a_step_settles_with_the_static_error_of_the_series_stiffness() -> None:
    _, angles = hold(SimHal("exo_dummy_arm"), 700.0, 20.0, seconds=3.0, offset=0.02)
    start = angles[0]
    final = angles[-1]
    # no feed-forward here: the link sags by what the spring and the motor loop let it
    assert np.abs(final - (start + 0.02)).max() < 0.02
    assert np.abs(angles[-500:] - final).max() < 5e-4  # and it stands still


def test_compiled_and_python_paths_give_the_same_commands(description: RobotDescription) -> None:
    full = load_waypoints()
    small = WaypointSet(
        waypoints=[full.waypoints[0], full.waypoints[13]], training_order=[1, 2], validation_order=[2, 1]
    )
    trajectory = build_trajectory(small, "training")  # starts at home, where the simulator starts
    ap = APModel.from_description(description, dummy_arm=True, elbow_stiffness=True)
    compiled = MotorPositionPD(description, trajectory, bounds(description), feedforward=ap)
    python = MotorPositionPD(description, lambda t: trajectory.reference(t), bounds(description), feedforward=ap)
    assert compiled._table is not None
    assert python._table is None
    hal = SimHal("exo_dummy_arm")
    hal.open()
    first = hal.read()
    for controller in (compiled, python):
        controller.reset(first)
    for n in range(3000):
        sample = hal.read()
        a, b = compiled.update(sample, 1e-3), python.update(sample, 1e-3)
        assert np.array_equal(a.motor_torque_nm, b.motor_torque_nm), n
        hal.write(a)


def test_reset_refuses_a_reference_far_from_the_robot(description: RobotDescription) -> None:
    hal = SimHal("exo_dummy_arm")
    hal.open()
    far = hal.read().q_rad + np.array([0.0, 0.2, 0.0, 0.0])
    controller = MotorPositionPD(description, lambda t: (far, np.zeros(4)), bounds(description))
    with pytest.raises(ControlError, match="joint 2"):
        controller.reset(hal.read())


def test_in_the_loop_it_tracks_with_feed_forward(description: RobotDescription) -> None:
    hal = SimHal("exo_dummy_arm")
    hal.open()
    first = hal.read()
    goal = first.q_rad + np.array([0.2, -0.2, 0.15, 0.3])

    def reference(t: float) -> tuple[np.ndarray, np.ndarray]:
        f = min(t / 2.0, 1.0)
        s = f**3 * (10 - 15 * f + 6 * f * f)
        ds = 30 * f * f * (1 - f) ** 2 / 2.0
        return first.q_rad + s * (goal - first.q_rad), ds * (goal - first.q_rad)

    ap = APModel.from_description(description, dummy_arm=True, elbow_stiffness=True)
    controller = MotorPositionPD(description, reference, bounds(description), feedforward=ap)
    controller.reset(first)
    loop = ControlLoop(hal, SafetyMonitor(SafetyLimits.from_description(description)), FixedSupervisor(controller),
                       LockStepClock(1e-3))  # fmt: skip
    errors = []
    loop.run(4000, on_tick=lambda r: errors.append(reference(r.sample.t_s)[0] - hal.truth().q_rad))
    errors = np.array(errors)
    assert np.sqrt(np.mean(errors**2, axis=0)).max() < 0.015
    assert np.abs(errors[-500:]).max() < 0.02
    assert isinstance(loop.tick().command, Command)


class _Wrapped(CompensationModel):
    """A model that is no LinearCompensationModel: it forwards to one and, when asked, offers its kernel."""

    kind = "wrapped"
    display_name = "wrapped"
    conservative_by_construction = True

    def __init__(self, inner: APModel, offer_kernel: bool) -> None:
        super().__init__(inner.description)
        self.inner, self.offer_kernel = inner, offer_kernel

    def torque(self, q: np.ndarray) -> np.ndarray:
        return self.inner.torque(q)

    def torque_batch(self, q: np.ndarray) -> np.ndarray:
        return self.inner.torque_batch(q)

    def tick_kernel(self) -> TickKernel | None:
        return self.inner.tick_kernel() if self.offer_kernel else None

    def parameters(self) -> dict[str, object]:
        return self.inner.parameters()

    @classmethod
    def from_parameters(cls, description: RobotDescription, parameters: object, name: str | None = None) -> _Wrapped:
        raise NotImplementedError


def test_the_compiled_path_follows_the_models_tick_kernel_not_its_class(description: RobotDescription) -> None:
    """Issue 11: the controller asks ``tick_kernel()``; the compiled and Python paths give the same commands."""
    full = load_waypoints()
    small = WaypointSet(
        waypoints=[full.waypoints[0], full.waypoints[13]], training_order=[1, 2], validation_order=[2, 1]
    )
    trajectory = build_trajectory(small, "training")
    ap = APModel.from_description(description, dummy_arm=True, elbow_stiffness=True)
    offered = MotorPositionPD(description, trajectory, bounds(description), feedforward=_Wrapped(ap, True))
    withheld = MotorPositionPD(description, trajectory, bounds(description), feedforward=_Wrapped(ap, False))
    assert offered._table is not None  # one compiled call per tick, the model inside it
    assert withheld._table is None  # the model's torque() in Python
    hal = SimHal("exo_dummy_arm")
    hal.open()
    first = hal.read()
    for controller in (offered, withheld):
        controller.reset(first)
    for n in range(1000):
        sample = hal.read()
        a, b = offered.update(sample, 1e-3), withheld.update(sample, 1e-3)
        assert np.array_equal(a.motor_torque_nm, b.motor_torque_nm), n
        hal.write(a)
