"""The dynamic plant (hal.sim.plant, hal.sim.dynamics): physics checked against independent paths.

* gravity against the static plant's CoM-Jacobian path (hal.sim.statics);
* M(q) against the Hessian of a kinetic energy built from finite differences of hal.robot's
  forward kinematics, and c(q, q') against Lagrange's equations on that M;
* energy: conserved without damping and motor torque, work-energy balance with inputs, never
  rising with damping alone;
* one joint against a hand-derived SEA pendulum; SEA mode frequencies; saturation; refusals.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from hal.errors import DescriptionError, HalError, InputError, ShapeError
from hal.robot import N_JOINTS, LinkInertial, RobotDescription, load_description
from hal.sim import dynamics
from hal.sim.plant import DynamicPlant
from hal.sim.scenario import Scenario, load_scenario

DESCRIPTION = load_description()
SCENARIOS = {name: load_scenario(name) for name in ("exo", "exo_dummy_arm")}
PLANTS = {name: DynamicPlant(scenario, DESCRIPTION) for name, scenario in SCENARIOS.items()}
#: Random configurations inside the device's range of motion (beyond it the end stops push back).
CONFIGURATIONS = np.random.default_rng(20261121).uniform(
    DESCRIPTION.lower_limits_rad, DESCRIPTION.upper_limits_rad, size=(25, N_JOINTS)
)
DT = 1e-3


def without_losses(scenario: Scenario) -> Scenario:
    """The scenario with every damping and friction term set to zero and the end stops out of reach.

    The released lossless arm swings through large angles; a stiff elastic end stop would turn
    that into a rigid-contact problem, which is not what the conservation test is about (the
    stops are tested on their own: test_end_stops_catch_an_arm_whose_torque_is_off).
    """
    assert scenario.drive_train is not None
    zero = [0.0] * N_JOINTS
    drive = scenario.drive_train.model_copy(
        update={
            "gearbox_viscous_nms_per_rad": zero,
            "gearbox_coulomb_nm": zero,
            "link_viscous_nms_per_rad": zero,
            "spring_damping_nms_per_rad": zero,
        }
    )
    stops = scenario.end_stops.model_copy(update={"damping_nms_per_rad": 0.0, "margin_deg": 3600.0})
    return scenario.model_copy(update={"drive_train": drive, "end_stops": stops})


def kinetic_energy_from_kinematics(scenario: Scenario, q: np.ndarray, dq: np.ndarray, h: float = 1e-6) -> float:
    """Kinetic energy of the links from central differences of hal.robot's forward kinematics.

    Every body's CoM velocity and angular velocity come from positions and orientations at
    ``q -+ h dq``; nothing of hal.sim.dynamics is used.
    """
    kinematics = DESCRIPTION.kinematics()
    bodies = [(i, link) for i, link in enumerate(scenario.links)]
    if scenario.dummy_arm is not None:
        bodies += [(2, scenario.dummy_arm.upper_arm), (3, scenario.dummy_arm.lower_arm)]
    q_pm = np.stack([q + h * dq, q - h * dq])
    rotations = kinematics.rotor_rotations(q_pm)
    origins = kinematics.frame_origins(q_pm)
    rotation_now = kinematics.rotor_rotations(q)[0]
    energy = 0.0
    for frame, body in bodies:
        com = origins[:, frame] + rotations[:, frame] @ np.asarray(body.com_m)
        velocity = (com[0] - com[1]) / (2 * h)
        skew = (rotations[0, frame] - rotations[1, frame]) / (2 * h) @ rotation_now[frame].T
        omega = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
        inertia_world = rotation_now[frame] @ np.diag(body.inertia_kgm2) @ rotation_now[frame].T
        energy += 0.5 * body.mass_kg * velocity @ velocity + 0.5 * omega @ inertia_world @ omega
    return float(energy)


# --- gravity and the mass matrix ------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_gravity_equals_the_static_plant(name: str) -> None:
    plant = PLANTS[name]
    static = SCENARIOS[name].static_plant(DESCRIPTION)
    expected = static.holding_torque_nm(CONFIGURATIONS)
    for q, tau in zip(CONFIGURATIONS, expected, strict=True):
        assert np.abs(plant.holding_torque_nm(q) - tau).max() < 1e-10


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_mass_matrix_is_symmetric_positive_definite(name: str) -> None:
    for q in CONFIGURATIONS:
        mass = PLANTS[name].mass_matrix(q)
        np.testing.assert_array_equal(mass, mass.T)
        assert np.linalg.eigvalsh(mass).min() > 1e-4


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_mass_matrix_is_the_hessian_of_the_kinetic_energy(name: str) -> None:
    scenario, plant = SCENARIOS[name], PLANTS[name]
    for q in CONFIGURATIONS[:4]:
        # T(dq) is quadratic, so the second difference with unit steps is exact up to rounding.
        hessian = np.empty((N_JOINTS, N_JOINTS))
        unit = np.eye(N_JOINTS)
        for j in range(N_JOINTS):
            for k in range(N_JOINTS):
                hessian[j, k] = (
                    kinetic_energy_from_kinematics(scenario, q, unit[j] + unit[k])
                    - kinetic_energy_from_kinematics(scenario, q, unit[j] - unit[k])
                    - kinetic_energy_from_kinematics(scenario, q, -unit[j] + unit[k])
                    + kinetic_energy_from_kinematics(scenario, q, -unit[j] - unit[k])
                ) / 4.0
        np.testing.assert_allclose(plant.mass_matrix(q), hessian, rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_coriolis_terms_follow_lagranges_equations(name: str) -> None:
    """``c(q, q') = Mdot q' - 1/2 d/dq (q'^T M q')`` with the derivatives of M by central differences."""
    plant = PLANTS[name]
    rng = np.random.default_rng(7)
    h = 1e-6
    for q in CONFIGURATIONS[:8]:
        dq = rng.uniform(-2.0, 2.0, N_JOINTS)
        d_mass = np.empty((N_JOINTS, N_JOINTS, N_JOINTS))  # d M / d q_k at [k]
        for k in range(N_JOINTS):
            step = np.zeros(N_JOINTS)
            step[k] = h
            d_mass[k] = (plant.mass_matrix(q + step) - plant.mass_matrix(q - step)) / (2 * h)
        m_dot = np.einsum("kij,k->ij", d_mass, dq)
        expected = m_dot @ dq - 0.5 * np.einsum("i,kij,j->k", dq, d_mass, dq)
        coriolis = plant.bias_torque(q, dq) - plant.bias_torque(q, np.zeros(N_JOINTS))
        np.testing.assert_allclose(coriolis, expected, rtol=1e-6, atol=1e-7)


# --- energy -----------------------------------------------------------------------------------------


def _released_away_from_equilibrium(plant: DynamicPlant) -> None:
    """At rest, links displaced from the initial configuration and springs deflected beyond holding."""
    q = plant.initial_q_rad + np.array([0.10, -0.10, 0.15, -0.20])
    theta = q + plant.holding_torque_nm(q) / plant.stiffness_nm_per_rad + np.array([0.02, -0.03, 0.02, 0.04])
    plant.set_state(q, np.zeros(N_JOINTS), theta, np.zeros(N_JOINTS))


def energy_drift(scenario: Scenario, dt_s: float, duration_s: float, single_step: bool = False) -> tuple[float, float]:
    """``(max |E(t) - E(0)|, max kinetic energy)`` of the lossless plant released away from equilibrium.

    ``single_step``: one RK4 step per ``dt_s`` instead of the plant's automatic substeps.
    """
    plant = DynamicPlant(without_losses(scenario), DESCRIPTION)
    _released_away_from_equilibrium(plant)
    inputs = np.zeros(2 * N_JOINTS)
    steps = round(duration_s / dt_s)
    energy = np.empty(steps + 1)
    kinetic = np.empty(steps + 1)
    energy[0], kinetic[0] = plant.energy_j(), plant.kinetic_energy_j()
    for n in range(1, steps + 1):
        if single_step:
            assert dynamics.rk4_step(plant.state, inputs, dt_s, plant.params, plant.work)
        else:
            plant.advance(inputs, dt_s)
        energy[n], kinetic[n] = plant.energy_j(), plant.kinetic_energy_j()
    return float(np.abs(energy - energy[0]).max()), float(kinetic.max())


# Both scenarios at the 1 kHz tick. Without the Dummy Arm the elbow's SEA mode is at 38 Hz, where a
# single RK4 step per tick would lose (w dt)^6 / 72 = 2.7e-6 of that mode's energy per step (0.7 %
# of the released energy in 10 s); the plant therefore takes two RK4 steps per tick there
# (DynamicPlant.substeps). docs/simulation.md has the figures.
@pytest.mark.parametrize("name", ["exo_dummy_arm", "exo"])
def test_energy_is_conserved_without_losses_or_motor_torque(name: str) -> None:
    drift, kinetic = energy_drift(SCENARIOS[name], 1e-3, 10.0)
    assert kinetic > 1.0  # the arm really moved: joules changed form
    assert drift < 1e-3 * kinetic, f"drift {drift:.3e} J, max kinetic {kinetic:.3f} J"


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_energy_drift_is_fourth_order_integration_error(name: str) -> None:
    """A non-conservative term would leave a drift that does not vanish with the step."""
    coarse, _ = energy_drift(SCENARIOS[name], 1e-3, 3.0, single_step=True)
    fine, _ = energy_drift(SCENARIOS[name], 5e-4, 3.0, single_step=True)
    assert fine < coarse / 16.0, (coarse, fine)


def test_the_exoskeleton_alone_takes_two_substeps_per_tick() -> None:
    assert DynamicPlant(SCENARIOS["exo"], DESCRIPTION).substeps(1e-3) == 2
    assert DynamicPlant(SCENARIOS["exo_dummy_arm"], DESCRIPTION).substeps(1e-3) == 1


def test_end_stops_catch_an_arm_whose_torque_is_off() -> None:
    """Torque off (FAIL), drives disabled: the arm falls, but the hard stops hold it near the limits."""
    plant = DynamicPlant(SCENARIOS["exo_dummy_arm"], DESCRIPTION)
    lower, upper = DESCRIPTION.lower_limits_rad, DESCRIPTION.upper_limits_rad
    q_seen, kinetic = [], []
    for _ in range(5000):
        plant.step(np.zeros(N_JOINTS), DT)
        q_seen.append(plant.q_rad.copy())
        kinetic.append(plant.kinetic_energy_j())
    q_seen = np.array(q_seen)
    margin = np.deg2rad(SCENARIOS["exo_dummy_arm"].end_stops.margin_deg)
    assert np.all(q_seen >= lower - margin - 0.05)  # a few degrees of stop compression at most
    assert np.all(q_seen <= upper + margin + 0.05)
    assert (q_seen < lower - 1e-3).any() or (q_seen > upper + 1e-3).any()  # it did reach a stop
    assert max(kinetic[-1000:]) < 0.2 * max(kinetic)  # stops and friction take the energy out


def test_work_of_the_inputs_equals_the_change_of_energy() -> None:
    """Without losses, E(t) - E(0) = integral of tau_m theta' + tau_ext q' (signs of both inputs)."""
    plant = DynamicPlant(without_losses(SCENARIOS["exo_dummy_arm"]), DESCRIPTION)
    holding = plant.holding_torque_nm(plant.q_rad)
    energy_start, work = plant.energy_j(), 0.0
    for n in range(2000):
        t = n * DT
        tau_m = holding + 2.0 * np.sin(2 * np.pi * 1.5 * t + np.arange(N_JOINTS))
        tau_ext = 1.0 * np.cos(2 * np.pi * 0.7 * t + np.arange(N_JOINTS))
        before = plant.truth()
        plant.step(tau_m, DT, tau_ext)
        after = plant.truth()
        # Trapezoidal power with inputs held over the step: exact to O(dt^3) per step.
        work += (
            DT * (tau_m @ (before.dtheta_rad_s + after.dtheta_rad_s) + tau_ext @ (before.dq_rad_s + after.dq_rad_s)) / 2
        )
    change = plant.energy_j() - energy_start
    assert abs(change) > 0.05
    assert change == pytest.approx(work, rel=2e-4, abs=1e-5)


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_damping_and_friction_only_remove_energy(name: str) -> None:
    plant = DynamicPlant(SCENARIOS[name], DESCRIPTION)
    _released_away_from_equilibrium(plant)
    energy = [plant.energy_j()]
    for _ in range(3000):
        plant.step(np.zeros(N_JOINTS), DT)
        energy.append(plant.energy_j())
    assert np.diff(energy).max() < 1e-6
    assert energy[-1] < energy[0] - 0.5


# --- equilibrium, one joint, modes ----------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_reset_is_a_static_equilibrium(name: str) -> None:
    plant = PLANTS[name]
    configurations = [None, np.array([0.3, -0.4, 0.8, 1.2]), np.array([-0.6, 1.0, -0.5, 0.2])]
    for q0 in configurations:
        plant.reset(q0)
        q_start = plant.q_rad
        holding = plant.holding_torque_nm(q_start)
        np.testing.assert_allclose(plant.spring_torque_nm(), holding, atol=1e-12)
        for _ in range(1000):  # 1 s
            plant.step(holding, DT)
        assert np.abs(plant.dq_rad_s).max() < 1e-9
        assert np.abs(plant.dtheta_rad_s).max() < 1e-9
        assert np.abs(plant.q_rad - q_start).max() < 1e-9
        assert plant.time_s == pytest.approx(1.0)
    plant.reset()


def test_elbow_matches_a_hand_derived_sea_pendulum() -> None:
    """Joint 4 alone: the lower link swinging about the elbow axis on its SEA, all losses included.

    Joints 1-3 are held by giving links 1-3 an enormous isotropic inertia (no gyroscopic terms),
    so the elbow is a one-link pendulum about a fixed axis whose equations are written by hand:
    ``I q'' = k (th - q) + d_s (th' - q') - b_l q' - m g d/dq (a . Rz(q) c)`` with ``a`` the
    world's up direction in rotor-3 coordinates, and the motor equation of the drive train.
    """
    scenario = SCENARIOS["exo"]
    heavy = [
        LinkInertial(mass_kg=link.mass_kg, com_m=link.com_m, inertia_kgm2=(1e6, 1e6, 1e6))
        for link in scenario.links[:3]
    ]
    scenario = scenario.model_copy(update={"links": [*heavy, scenario.links[3]]})
    plant = DynamicPlant(scenario, DESCRIPTION)
    drive = scenario.drive_train
    assert drive is not None
    link = scenario.links[3]
    assert link.inertia_kgm2 is not None
    mass, (cx, cy, _cz), izz = link.mass_kg, link.com_m, link.inertia_kgm2[2]
    g, k = scenario.gravity_mps2, DESCRIPTION.sea.spring_stiffness_nm_per_rad
    inertia = izz + mass * (cx**2 + cy**2)  # parallel axes: the elbow axis is rotor 4's z
    jm, bm, tc = drive.gearbox_inertia_kgm2[3], drive.gearbox_viscous_nms_per_rad[3], drive.gearbox_coulomb_nm[3]
    bl, ds, eps = drive.link_viscous_nms_per_rad[3], drive.spring_damping_nms_per_rad[3], drive.coulomb_smoothing_rad_s

    q_fixed = plant.initial_q_rad
    rotor3 = DESCRIPTION.kinematics().rotor_rotations(q_fixed)[0, 2]
    ax, ay, _ = rotor3.T @ np.array([0.0, 1.0, 0.0])

    def gravity(q4: float) -> float:
        return mass * g * (ax * (-cx * np.sin(q4) - cy * np.cos(q4)) + ay * (cx * np.cos(q4) - cy * np.sin(q4)))

    tau_m = plant.holding_torque_nm(q_fixed)  # every motor holds the initial posture
    assert tau_m[3] == pytest.approx(gravity(q_fixed[3]), abs=1e-12)

    def pendulum(_t: float, y: np.ndarray) -> list[float]:
        q4, th, dq4, dth = y
        spring = k * (th - q4) + ds * (dth - dq4)
        return [
            dq4,
            dth,
            (spring - bl * dq4 - gravity(q4)) / inertia,
            (tau_m[3] - spring - bm * dth - tc * np.tanh(dth / eps)) / jm,
        ]

    # Turn the elbow 0.3 rad from equilibrium, its motor 0.25 rad: gravity and a spring 0.05 rad
    # off its holding deflection (14 Nm) set it swinging and ringing.
    q0, theta0 = plant.q_rad, plant.theta_rad
    q0[3] += 0.3
    theta0[3] += 0.25
    plant.set_state(q0, np.zeros(N_JOINTS), theta0, np.zeros(N_JOINTS))
    steps = 2000
    simulated = np.empty((steps, 2))
    for n in range(steps):
        plant.step(tau_m, DT)
        simulated[n] = plant.q_rad[3], plant.theta_rad[3]
    assert np.ptp(simulated[:, 0]) > 0.05  # it moved

    # The same classical RK4 on the hand-derived equations: equal up to the held joints' creep.
    y = np.array([q0[3], theta0[3], 0.0, 0.0])
    by_hand = np.empty((steps, 2))
    for n in range(steps):
        k1 = np.array(pendulum(0.0, y))
        k2 = np.array(pendulum(0.0, y + 0.5 * DT * k1))
        k3 = np.array(pendulum(0.0, y + 0.5 * DT * k2))
        k4 = np.array(pendulum(0.0, y + DT * k3))
        y = y + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        by_hand[n] = y[:2]
    np.testing.assert_allclose(simulated, by_hand, rtol=0, atol=1e-7)
    # And the 1 kHz step is accurate against a tight adaptive integration of the same equations.
    times = np.arange(1, steps + 1) * DT
    reference = solve_ivp(
        pendulum, (0.0, times[-1]), [q0[3], theta0[3], 0.0, 0.0], t_eval=times, rtol=1e-11, atol=1e-12, method="DOP853"
    )
    np.testing.assert_allclose(simulated, reference.y[:2].T, rtol=0, atol=1e-4)
    assert np.abs(plant.q_rad[:3] - q_fixed[:3]).max() < 1e-5  # joints 1-3 stayed put


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_sea_modes_are_a_few_hz_to_tens_of_hz(name: str) -> None:
    plant = PLANTS[name]
    free = plant.mode_frequencies_hz()
    locked = plant.mode_frequencies_hz(motor="locked")
    assert free.shape == (8,)
    assert locked.shape == (4,)
    # The four SEA modes (motor against link across the spring) and the locked-motor link modes.
    assert np.all((free[4:] > 3.0) & (free[4:] < 60.0)), free
    assert np.all((locked > 2.0) & (locked < 60.0)), locked
    # The four low modes swing motor and link together against gravity alone: below 2 Hz.
    assert np.all(np.abs(free[:4]) < 2.0), free
    # The kernel's own linearisation (numerical Jacobian), without losses, oscillates at the same
    # frequencies. (With losses it does not: at rest the smoothed Coulomb friction is a viscous
    # term of tau_c / eps = 20-40 Nms/rad that nearly locks the motors.)
    lossless = DynamicPlant(without_losses(SCENARIOS[name]), DESCRIPTION)
    eigenvalues = np.linalg.eigvals(lossless.linearise())
    assert np.abs(eigenvalues.real).max() < 2 * np.pi * 2.0  # only the gravity modes may be real
    oscillating_hz = np.sort(eigenvalues.imag[eigenvalues.imag > 2 * np.pi * 3.0]) / (2 * np.pi)
    np.testing.assert_allclose(oscillating_hz, free[4:], rtol=1e-5)


def test_stable_step_covers_the_tick_of_the_shipped_scenarios() -> None:
    for plant in PLANTS.values():
        assert plant.max_dt_s > 2e-3  # 1 kHz with a margin of two


# --- saturation and refusals ------------------------------------------------------------------------


def test_motor_torque_saturates() -> None:
    plant = PLANTS["exo"]
    limit = plant.max_motor_torque_nm
    for sign in (1.0, -1.0):
        plant.reset()
        plant.step(sign * 1000.0 * np.ones(N_JOINTS), DT)
        beyond = plant.truth()
        plant.reset()
        plant.step(sign * limit, DT)
        at_limit = plant.truth()
        np.testing.assert_array_equal(beyond.theta_rad, at_limit.theta_rad)
        np.testing.assert_array_equal(beyond.dtheta_rad_s, at_limit.dtheta_rad_s)
        assert np.all(sign * at_limit.dtheta_rad_s > 0.1)  # 40 Nm on ~0.25 kg m^2 for 1 ms
    plant.reset()


def test_a_scenario_without_drive_train_is_refused() -> None:
    scenario = SCENARIOS["exo"].model_copy(update={"drive_train": None})
    with pytest.raises(DescriptionError, match="drive_train"):
        DynamicPlant(scenario, DESCRIPTION)


def test_a_body_without_inertia_is_refused_by_name() -> None:
    scenario = SCENARIOS["exo_dummy_arm"]
    links = list(scenario.links)
    links[2] = LinkInertial(mass_kg=links[2].mass_kg, com_m=links[2].com_m)
    with pytest.raises(DescriptionError, match=r"links\.2\.inertia_kgm2"):
        DynamicPlant(scenario.model_copy(update={"links": links}), DESCRIPTION)
    assert scenario.dummy_arm is not None
    arm = scenario.dummy_arm.model_copy(update={"lower_arm": LinkInertial(mass_kg=1.0, com_m=(0.1, 0.0, 0.0))})
    with pytest.raises(DescriptionError, match=r"dummy_arm\.lower_arm\.inertia_kgm2"):
        DynamicPlant(scenario.model_copy(update={"dummy_arm": arm}), DESCRIPTION)


def test_unphysical_drive_train_and_inertia_are_refused() -> None:
    scenario = SCENARIOS["exo"]
    assert scenario.drive_train is not None
    drive = scenario.drive_train.model_copy(update={"gearbox_inertia_kgm2": [0.27, 0.0, 0.26, 0.24]})
    with pytest.raises(DescriptionError, match=r"gearbox_inertia_kgm2, joint 2"):
        DynamicPlant(scenario.model_copy(update={"drive_train": drive}), DESCRIPTION)
    drive = scenario.drive_train.model_copy(update={"link_viscous_nms_per_rad": [0.05, 0.05, -0.01, 0.03]})
    with pytest.raises(DescriptionError, match=r"link_viscous_nms_per_rad, joint 3"):
        DynamicPlant(scenario.model_copy(update={"drive_train": drive}), DESCRIPTION)
    links = list(scenario.links)
    links[0] = LinkInertial(mass_kg=1.0, com_m=(0.1, 0.0, 0.0), inertia_kgm2=(0.001, 0.001, 0.01))
    with pytest.raises(DescriptionError, match="not a rigid body"):
        DynamicPlant(scenario.model_copy(update={"links": links}), DESCRIPTION)


def test_step_refuses_bad_arguments_and_keeps_the_state() -> None:
    plant = PLANTS["exo"]
    plant.reset()
    before = plant.truth()
    with pytest.raises(ShapeError):
        plant.step(np.zeros(3), DT)
    with pytest.raises(ShapeError):
        plant.step(np.zeros(N_JOINTS), DT, np.zeros((2, 4)))
    with pytest.raises(InputError):
        plant.step(np.array([0.0, np.nan, 0.0, 0.0]), DT)
    for dt in (0.0, -DT, np.inf, np.nan, 1.0):
        with pytest.raises(InputError):
            plant.step(np.zeros(N_JOINTS), dt)
    with pytest.raises(HalError, match="diverged"):
        plant.step(np.zeros(N_JOINTS), DT, np.full(N_JOINTS, 1e308))
    after = plant.truth()
    for a, b in zip(before, after, strict=True):
        np.testing.assert_array_equal(a, b)
    assert plant.time_s == 0.0


def test_plant_built_from_a_description_with_other_stiffness() -> None:
    """The SEA stiffness comes from the robot description, not the scenario."""
    soft = RobotDescription.model_validate(
        DESCRIPTION.model_dump() | {"sea": DESCRIPTION.sea.model_dump() | {"spring_stiffness_nm_per_rad": 150.0}}
    )
    plant = DynamicPlant(SCENARIOS["exo"], soft)
    np.testing.assert_array_equal(plant.stiffness_nm_per_rad, 150.0)
    deflection = plant.theta_rad - plant.q_rad
    np.testing.assert_allclose(150.0 * deflection, plant.holding_torque_nm(plant.q_rad), atol=1e-12)
