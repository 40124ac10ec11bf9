"""The dynamic simulated plant: rigid-body DAROR-01 chain, one series elastic actuator per joint.

:class:`DynamicPlant` turns a scenario's as-built truth (link masses, centres of mass and
inertias, the Dummy Arm and its elbow springs, the drive train, and the undeclared effects
mounting tilt, joint springs and SEA stiffness scale) into the parameter vector of the numba kernels in :mod:`hal.sim.dynamics` and owns the state ``(q, q', theta, theta')``. The
physics and the integrator are documented there and in ``docs/simulation.md``.

Gravity here is the same physics as :class:`hal.sim.statics.StaticPlant` (world positions of the
bodies' centres of mass and their Jacobians), computed by an independent code path; a test holds
the two equal to 1e-10 Nm.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple

import numpy as np
import scipy.linalg

from hal.errors import DescriptionError, HalError, InputError, ShapeError
from hal.robot import N_JOINTS, FloatArray, LinkInertial, RobotDescription
from hal.sim import dynamics
from hal.sim.dynamics import N_INPUT, N_STATE
from hal.sim.scenario import Scenario

#: The plant refuses steps longer than this fraction of the RK4 stability limit (linearised plant).
STABILITY_MARGIN = 0.5
#: Largest angular frequency times step of the fastest mode that RK4 may take (see DynamicPlant.substeps).
MAX_OMEGA_STEP = 0.2

_Q = slice(0, N_JOINTS)
_THETA = slice(N_JOINTS, 2 * N_JOINTS)
_DQ = slice(2 * N_JOINTS, 3 * N_JOINTS)
_DTHETA = slice(3 * N_JOINTS, 4 * N_JOINTS)


class PlantTruth(NamedTuple):
    """The true state of the plant (tests only: the runtime sees :class:`hal.interface.Sample`).

    ``tau_spring_nm`` is the torque the SEA springs apply to the links, ``k (theta - q) + d_s
    (theta' - q')``. Arrays of shape (4,): rad, rad/s, Nm.
    """

    q_rad: FloatArray
    dq_rad_s: FloatArray
    theta_rad: FloatArray
    dtheta_rad_s: FloatArray
    tau_spring_nm: FloatArray


#: A rest support under the arm (a lap, an armrest): push-only per joint, softer than an end stop (Nm/rad, Nms/rad).
REST_SUPPORT_STIFFNESS_NM_PER_RAD = 400.0
REST_SUPPORT_DAMPING_NMS_PER_RAD = 4.0
#: A joint that holds less than this at the rest pose needs no support there (Nm).
REST_SUPPORT_MIN_NM = 0.05


def joint_vector(value: object, name: str) -> FloatArray:
    """``value`` as a finite float (4,) array.

    Raises:
        ShapeError: not of shape (4,).
        InputError: a non-finite element.
    """
    array = np.asarray(value, dtype=np.float64)
    if array.shape != (N_JOINTS,):
        raise ShapeError(f"{name}: expected shape ({N_JOINTS},), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InputError(f"{name}: every element must be finite, got {array.tolist()}")
    return array


def _body_part(scenario: Scenario, field: str, part: LinkInertial) -> tuple[float, FloatArray, FloatArray]:
    """Mass, CoM and principal inertias of one body, checked for a dynamic simulation.

    Raises:
        DescriptionError: the inertia is missing or not physical.
    """
    if part.inertia_kgm2 is None:
        raise DescriptionError(
            f"scenario {scenario.name!r}: field {field}.inertia_kgm2 is missing; "
            "the dynamic plant needs the inertia of every body"
        )
    inertia = np.asarray(part.inertia_kgm2, dtype=float)
    ixx, iyy, izz = inertia
    if np.any(inertia < 0) or ixx > iyy + izz or iyy > ixx + izz or izz > ixx + iyy:
        raise DescriptionError(
            f"scenario {scenario.name!r}: field {field}.inertia_kgm2 = {inertia.tolist()} is not a rigid body's "
            "(principal moments must be non-negative and each at most the sum of the other two)"
        )
    return part.mass_kg, np.asarray(part.com_m, dtype=float), np.diag(inertia)


def composite_bodies(scenario: Scenario) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One rigid body per rotor frame: links plus the Dummy Arm segments attached to them.

    Returns:
        mass (4,) kg, CoM (4, 3) m in each rotor frame, inertia about that CoM (4, 3, 3) kg m^2.

    Raises:
        DescriptionError: a body's inertia is missing or not physical.
    """
    parts: list[list[tuple[float, FloatArray, FloatArray]]] = [[] for _ in range(N_JOINTS)]
    for i, link in enumerate(scenario.links):
        parts[i].append(_body_part(scenario, f"links.{i}", link))
    if scenario.dummy_arm is not None:
        # Frames as in Scenario.static_plant: upper arm on rotor 3, lower arm on rotor 4.
        parts[2].append(_body_part(scenario, "dummy_arm.upper_arm", scenario.dummy_arm.upper_arm))
        parts[3].append(_body_part(scenario, "dummy_arm.lower_arm", scenario.dummy_arm.lower_arm))
    mass = np.zeros(N_JOINTS)
    com = np.zeros((N_JOINTS, 3))
    inertia = np.zeros((N_JOINTS, 3, 3))
    for i, frame_parts in enumerate(parts):
        mass[i] = sum(m for m, _, _ in frame_parts)
        com[i] = sum(m * c for m, c, _ in frame_parts) / mass[i]
        for m, c, inertia_about_own_com in frame_parts:
            r = c - com[i]  # parallel-axis theorem to the composite CoM
            inertia[i] += inertia_about_own_com + m * (r @ r * np.eye(3) - np.outer(r, r))
    return mass, com, inertia


def _per_joint(scenario: Scenario, field: str, values: list[float], positive: bool) -> FloatArray:
    """A per-joint drive-train value, checked.

    Raises:
        DescriptionError: a value is not finite, or not positive (``positive``) / negative.
    """
    array = np.asarray(values, dtype=float)
    for j, value in enumerate(array, start=1):
        if not np.isfinite(value) or (value <= 0 if positive else value < 0):
            bound = "positive" if positive else "non-negative"
            raise DescriptionError(
                f"scenario {scenario.name!r}: field drive_train.{field}, joint {j}: {value} must be {bound} and finite"
            )
    return array


class DynamicPlant:
    """Rigid-body dynamics of the DAROR-01 with its SEAs, as one scenario declares it.

    State: link angles ``q``, motor-side angles ``theta`` (gearbox output, before the spring) and
    their rates. Construction starts the plant at rest in static equilibrium at the scenario's
    ``initial_q_deg``.

    Raises (constructor):
        DescriptionError: the scenario has no ``drive_train``, a body without ``inertia_kgm2``, or
            a drive-train value that is not physical.
    """

    def __init__(self, scenario: Scenario, description: RobotDescription | None = None) -> None:
        self.scenario = scenario
        self.description = description or scenario.description()
        drive = scenario.drive_train
        if drive is None:
            raise DescriptionError(
                f"scenario {scenario.name!r}: field drive_train is missing; "
                "the dynamic plant needs the as-built drive train of every SEA"
            )
        mass, com, inertia = composite_bodies(scenario)
        # As built: the base's mounting tilt is in the chain the kernels get (the same chain as
        # Scenario.static_plant's, so gravity agrees with the static plant's).
        kinematics = scenario.true_kinematics(self.description)
        #: As-built SEA spring constants (4,) Nm/rad: nominal x sensors' ``sea_stiffness_scale``.
        #: The simulated drives compute torque with the nominal constant (hal.sim.backend).
        self.stiffness_nm_per_rad = scenario.stiffness_nm_per_rad(self.description)
        self.spring_damping_nms_per_rad = _per_joint(
            scenario, "spring_damping_nms_per_rad", drive.spring_damping_nms_per_rad, False
        )
        self.motor_inertia_kgm2 = _per_joint(scenario, "gearbox_inertia_kgm2", drive.gearbox_inertia_kgm2, True)
        self.max_motor_torque_nm = _per_joint(scenario, "max_motor_torque_nm", drive.max_motor_torque_nm, True)
        self.command_delay_ticks = drive.command_delay_ticks
        springs = []
        if scenario.dummy_arm is not None:
            springs = [
                (
                    3,
                    s.stiffness_nm_per_rad,
                    float(np.deg2rad(s.slack_angle_deg)),
                    1.0 if s.resists == "flexion" else -1.0,
                )
                for s in scenario.dummy_arm.elbow_springs
            ]
        # Undeclared two-sided joint springs: the static plant's flexion/extension pair, undamped.
        springs += [
            (s.joint - 1, s.stiffness_nm_per_rad, s.slack_angle_rad, 1.0 if s.resists == "flexion" else -1.0)
            for s in scenario.joint_pull_springs()
        ]
        stops = scenario.end_stops
        margin = np.deg2rad(stops.margin_deg)
        for j, (lower, upper) in enumerate(
            zip(self.description.lower_limits_rad, self.description.upper_limits_rad, strict=True)
        ):
            springs.append((j, stops.stiffness_nm_per_rad, float(upper + margin), 1.0, stops.damping_nms_per_rad))
            springs.append((j, stops.stiffness_nm_per_rad, float(lower - margin), -1.0, stops.damping_nms_per_rad))
        #: Parameter vector of the kernels (layout in hal.sim.dynamics).
        self.params = dynamics.pack_parameters(
            base_rotation=kinematics.base_rotation,
            inter_rotation=kinematics.inter_rotation,
            elbow_offset_m=kinematics.elbow_offset_m,
            gravity_mps2=scenario.gravity_mps2,
            body_mass_kg=mass,
            body_com_m=com,
            body_inertia_kgm2=inertia,
            stiffness_nm_per_rad=self.stiffness_nm_per_rad,
            spring_damping_nms_per_rad=self.spring_damping_nms_per_rad,
            link_viscous_nms_per_rad=_per_joint(
                scenario, "link_viscous_nms_per_rad", drive.link_viscous_nms_per_rad, False
            ),
            motor_inertia_kgm2=self.motor_inertia_kgm2,
            motor_viscous_nms_per_rad=_per_joint(
                scenario, "gearbox_viscous_nms_per_rad", drive.gearbox_viscous_nms_per_rad, False
            ),
            motor_coulomb_nm=_per_joint(scenario, "gearbox_coulomb_nm", drive.gearbox_coulomb_nm, False),
            max_motor_torque_nm=self.max_motor_torque_nm,
            coulomb_smoothing_rad_s=drive.coulomb_smoothing_rad_s,
            springs=springs,
        )
        self._fixed_springs = int(self.params[dynamics.P_N_SPRINGS])  # the scenario's; a rest support goes after them
        #: The state [q, theta, q', theta'] (16,); the simulated HAL steps it in place.
        self.state = np.zeros(N_STATE)
        self.work = dynamics.new_work()
        self._u = np.zeros(N_INPUT)
        self._energy = np.zeros(5)
        self.time_s = 0.0
        self.initial_q_rad = np.deg2rad(np.asarray(scenario.initial_q_deg, dtype=float))
        self.reset()
        #: Longest step :meth:`step` accepts: STABILITY_MARGIN times the RK4 stability limit of
        #: the plant linearised at rest at the initial configuration (s).
        self.max_dt_s = STABILITY_MARGIN * self.rk4_stability_limit_s()
        self._substeps: dict[float, int] = {}

    # --- state ----------------------------------------------------------------------------------

    def reset(self, q0_rad: FloatArray | None = None) -> None:
        """Rest in static equilibrium at ``q0_rad`` (default the scenario's ``initial_q_deg``); time 0.

        ``theta = q + g(q) / k``: each spring carries the holding torque, so a constant motor
        torque ``g(q)`` keeps the plant still.

        Raises:
            ShapeError: ``q0_rad`` is not of shape (4,).
            InputError: ``q0_rad`` has a non-finite element.
        """
        q = self.initial_q_rad if q0_rad is None else joint_vector(q0_rad, "q0_rad")
        self.state[:] = 0.0
        self.state[_Q] = q
        self.state[_THETA] = q + self.holding_torque_nm(q) / self.stiffness_nm_per_rad
        self.time_s = 0.0

    def set_state(
        self, q_rad: FloatArray, dq_rad_s: FloatArray, theta_rad: FloatArray, dtheta_rad_s: FloatArray
    ) -> None:
        """Put the plant in an arbitrary state (tests: start away from equilibrium).

        Raises:
            ShapeError: an array not of shape (4,).
            InputError: a non-finite element.
        """
        self.state[_Q] = joint_vector(q_rad, "q_rad")
        self.state[_DQ] = joint_vector(dq_rad_s, "dq_rad_s")
        self.state[_THETA] = joint_vector(theta_rad, "theta_rad")
        self.state[_DTHETA] = joint_vector(dtheta_rad_s, "dtheta_rad_s")

    @property
    def q_rad(self) -> FloatArray:
        return self.state[_Q].copy()

    @property
    def dq_rad_s(self) -> FloatArray:
        return self.state[_DQ].copy()

    @property
    def theta_rad(self) -> FloatArray:
        return self.state[_THETA].copy()

    @property
    def dtheta_rad_s(self) -> FloatArray:
        return self.state[_DTHETA].copy()

    def spring_torque_nm(self) -> FloatArray:
        """Torque the SEA springs apply to the links now, ``k (theta - q) + d_s (theta' - q')`` (4,)."""
        x = self.state
        return self.stiffness_nm_per_rad * (x[_THETA] - x[_Q]) + self.spring_damping_nms_per_rad * (x[_DTHETA] - x[_DQ])

    def truth(self) -> PlantTruth:
        """Copies of the true state and spring torque."""
        return PlantTruth(self.q_rad, self.dq_rad_s, self.theta_rad, self.dtheta_rad_s, self.spring_torque_nm())

    # --- time -----------------------------------------------------------------------------------

    def step(self, motor_torque_nm: FloatArray, dt_s: float, external_torque_nm: FloatArray | None = None) -> None:
        """Advance by ``dt_s`` with classical RK4 (:meth:`substeps` steps), inputs held constant.

        Args:
            motor_torque_nm: (4,) motor torque at the gearbox output; saturated at
                ``max_motor_torque_nm`` inside the plant.
            dt_s: step length, positive and at most :attr:`max_dt_s`.
            external_torque_nm: (4,) torque on the links from outside (the pilot), default zero.

        Raises:
            ShapeError: a torque not of shape (4,).
            InputError: a non-finite torque, or ``dt_s`` not in (0, max_dt_s].
            HalError: the integration diverged (non-finite state); the state is left as before.
        """
        self._u[:N_JOINTS] = joint_vector(motor_torque_nm, "motor_torque_nm")
        if external_torque_nm is None:
            self._u[N_JOINTS:] = 0.0
        else:
            self._u[N_JOINTS:] = joint_vector(external_torque_nm, "external_torque_nm")
        if not (np.isfinite(dt_s) and 0.0 < dt_s <= self.max_dt_s):
            raise InputError(
                f"dt_s = {dt_s}: must be positive and at most {self.max_dt_s:.3g} s "
                f"(half the RK4 stability limit of scenario {self.scenario.name!r})"
            )
        self.advance(self._u, dt_s)

    def substeps(self, dt_s: float) -> int:
        """RK4 steps per ``dt_s`` that keep the fastest mode's energy error negligible.

        Stable is not enough: RK4 damps a mode of angular frequency w by about (w h)^6 / 72 of
        its energy per step. Keeping ``w h <= MAX_OMEGA_STEP`` holds the energy drift of 10 s
        under 0.1 % (docs/simulation.md); the exoskeleton alone has a 38 Hz elbow mode that
        needs two steps per 1 ms tick, the Dummy Arm lowers it to 25 Hz and one step suffices.
        """
        if dt_s not in self._substeps:
            fastest = 2 * np.pi * float(np.max(np.abs(self.mode_frequencies_hz(motor="free"))))
            self._substeps[dt_s] = max(1, math.ceil(fastest * dt_s / MAX_OMEGA_STEP))
        return self._substeps[dt_s]

    def advance(self, inputs: FloatArray, dt_s: float) -> None:
        """:meth:`step` without argument checks: ``inputs = [tau_m, tau_ext]`` (8,) float64.

        For the simulated HAL, which has checked its inputs already.

        Raises:
            HalError: the integration diverged (non-finite state); the state is left as before.
        """
        n = self.substeps(dt_s)
        if dynamics.simulate(self.state, inputs, dt_s / n, n, self.params, self.work) != n:
            raise HalError(
                f"simulated plant diverged at t = {self.time_s:.6f} s (scenario {self.scenario.name!r}); "
                f"state q = {self.state[_Q].tolist()} rad kept from the last good substep"
            )
        self.time_s += dt_s

    # --- physics queries ------------------------------------------------------------------------

    def mass_matrix(self, q_rad: FloatArray) -> FloatArray:
        """Link-side mass matrix ``M(q)`` (4, 4), kg m^2.

        Raises:
            ShapeError, InputError: ``q_rad`` not a finite (4,) array.
        """
        out = np.empty((N_JOINTS, N_JOINTS))
        dynamics.mass_matrix(joint_vector(q_rad, "q_rad"), self.params, self.work, out)
        return out

    def bias_torque(self, q_rad: FloatArray, dq_rad_s: FloatArray) -> FloatArray:
        """``c(q, q') + g(q)`` (4,), Nm: Coriolis/centrifugal plus holding torque.

        Raises:
            ShapeError, InputError: an argument not a finite (4,) array.
        """
        out = np.empty(N_JOINTS)
        q = joint_vector(q_rad, "q_rad")
        dynamics.bias_torque(q, joint_vector(dq_rad_s, "dq_rad_s"), self.params, self.work, out)
        return out

    def place_rest_support(self, q_rad: FloatArray | None) -> int:
        """Put something under the arm at ``q_rad`` (a pilot's lap, an armrest, a tray); None takes it away.

        Per joint that gravity (and the springs) pull one way at ``q_rad``, a push-only, damped
        support that keeps the joint from going farther that way: :data:`REST_SUPPORT_STIFFNESS_NM_PER_RAD`,
        :data:`REST_SUPPORT_DAMPING_NMS_PER_RAD` (softer than an end stop: a lap gives a little). Joints
        that hold less than :data:`REST_SUPPORT_MIN_NM` there need none. Returns how many joints it supports.

        Raises:
            ShapeError, InputError: ``q_rad`` not a finite (4,) array.
        """
        n = self._fixed_springs
        self.params[dynamics.P_N_SPRINGS] = n
        if q_rad is None:
            return 0
        q = joint_vector(q_rad, "rest pose")
        holding = self.holding_torque_nm(q)
        placed = 0
        for j in range(N_JOINTS):
            if abs(holding[j]) < REST_SUPPORT_MIN_NM:
                continue
            # Holding needs +g: gravity pulls the joint towards smaller angles, which the support stops.
            resists = -1.0 if holding[j] > 0 else 1.0
            base = dynamics.P_SPRINGS + (n + placed) * dynamics.SPRING_SIZE
            self.params[base : base + dynamics.SPRING_SIZE] = (
                j, REST_SUPPORT_STIFFNESS_NM_PER_RAD, q[j], resists, REST_SUPPORT_DAMPING_NMS_PER_RAD,
            )  # fmt: skip
            placed += 1
        self.params[dynamics.P_N_SPRINGS] = n + placed
        return placed

    def holding_torque_nm(self, q_rad: FloatArray) -> FloatArray:
        """``g(q) = dV/dq`` (4,), Nm: gravity of every body plus the pull-only joint springs.

        Raises:
            ShapeError, InputError: ``q_rad`` not a finite (4,) array.
        """
        return self.bias_torque(q_rad, np.zeros(N_JOINTS))

    def energy_components_j(self) -> dict[str, float]:
        """Mechanical energy terms now, J (gravity potential is zero at the height of the CoR)."""
        dynamics.energy_components(self.state, self.params, self.work, self._energy)
        names = ("link_kinetic", "motor_kinetic", "gravity_potential", "sea_spring_potential", "joint_spring_potential")
        return dict(zip(names, self._energy.tolist(), strict=True))

    def energy_j(self) -> float:
        """Total mechanical energy now, J: link and motor kinetic, gravity, SEA and joint springs."""
        dynamics.energy_components(self.state, self.params, self.work, self._energy)
        return float(self._energy.sum())

    def kinetic_energy_j(self) -> float:
        """Link plus motor kinetic energy now, J."""
        dynamics.energy_components(self.state, self.params, self.work, self._energy)
        return float(self._energy[0] + self._energy[1])

    def state_derivative(
        self, state: FloatArray, motor_torque_nm: FloatArray, external_torque_nm: FloatArray
    ) -> FloatArray:
        """``dx/dt`` (16,) at ``state`` ``[q, theta, q', theta']`` with the given torques.

        Raises:
            ShapeError: an argument of the wrong shape.
            HalError: ``M(q)`` is not positive definite at ``state``.
        """
        x = np.asarray(state, dtype=np.float64)
        if x.shape != (N_STATE,):
            raise ShapeError(f"state: expected shape ({N_STATE},), got {x.shape}")
        u = np.concatenate(
            [joint_vector(motor_torque_nm, "motor_torque_nm"), joint_vector(external_torque_nm, "external_torque_nm")]
        )
        out = np.empty(N_STATE)
        if not dynamics.derivative(x, u, self.params, self.work, out):
            raise HalError(f"mass matrix not positive definite at q = {x[_Q].tolist()}")
        return out

    # --- linearisation --------------------------------------------------------------------------

    def equilibrium_state(self, q_rad: FloatArray | None = None) -> FloatArray:
        """The rest state in static equilibrium at ``q_rad`` (default the initial configuration), (16,)."""
        q = self.initial_q_rad if q_rad is None else joint_vector(q_rad, "q_rad")
        x = np.zeros(N_STATE)
        x[_Q] = q
        x[_THETA] = q + self.holding_torque_nm(q) / self.stiffness_nm_per_rad
        return x

    def linearise(self, q_rad: FloatArray | None = None) -> FloatArray:
        """State matrix ``A = df/dx`` (16, 16) about rest in equilibrium at ``q_rad``.

        The motor torque is held at the holding torque (open loop), so ``A`` includes the
        drive-train damping and the slope ``tau_c / eps`` of the smoothed Coulomb friction.
        Central differences with 1e-7 steps.
        """
        x0 = self.equilibrium_state(q_rad)
        tau_m = self.holding_torque_nm(x0[_Q])
        zero = np.zeros(N_JOINTS)
        a = np.empty((N_STATE, N_STATE))
        h = 1e-7
        for n in range(N_STATE):
            step = np.zeros(N_STATE)
            step[n] = h
            a[:, n] = (
                self.state_derivative(x0 + step, tau_m, zero) - self.state_derivative(x0 - step, tau_m, zero)
            ) / (2 * h)
        return a

    def mode_frequencies_hz(
        self, q_rad: FloatArray | None = None, motor: Literal["free", "locked"] = "free"
    ) -> FloatArray:
        """Undamped natural frequencies of the plant linearised at rest at ``q_rad``, Hz, ascending.

        ``motor="free"``: motor torque constant (open loop), 8 modes: 4 low ones where motor and
        link swing together against the gravity stiffness, 4 SEA modes where they swing against
        each other across the springs. ``motor="locked"``: motor angles fixed (an ideally stiff
        motor position loop), 4 modes of the links on the springs. A negative value ``-f`` marks a
        statically unstable mode that grows like ``exp(2 pi f t)``.
        """
        q = self.initial_q_rad if q_rad is None else joint_vector(q_rad, "q_rad")
        mass = self.mass_matrix(q)
        h = 1e-6
        gravity_stiffness = np.empty((N_JOINTS, N_JOINTS))
        for j in range(N_JOINTS):
            step = np.zeros(N_JOINTS)
            step[j] = h
            gravity_stiffness[:, j] = (self.holding_torque_nm(q + step) - self.holding_torque_nm(q - step)) / (2 * h)
        gravity_stiffness = 0.5 * (gravity_stiffness + gravity_stiffness.T)  # a Hessian; remove FD asymmetry
        k = np.diag(self.stiffness_nm_per_rad)
        if motor == "locked":
            stiffness, inertia = k + gravity_stiffness, mass
        elif motor == "free":
            stiffness = np.block([[k + gravity_stiffness, -k], [-k, k]])
            inertia = scipy.linalg.block_diag(mass, np.diag(self.motor_inertia_kgm2))
        else:
            raise InputError(f"motor = {motor!r}; expected 'free' or 'locked'")
        eigenvalues = scipy.linalg.eigh(stiffness, inertia, eigvals_only=True)
        return np.sign(eigenvalues) * np.sqrt(np.abs(eigenvalues)) / (2 * np.pi)

    def rk4_stability_limit_s(self, q_rad: FloatArray | None = None) -> float:
        """Longest step for which RK4 is stable on the plant linearised at rest at ``q_rad``, s.

        Modes that grow physically (a statically unstable posture) are judged by their
        oscillatory part only; their growth is physics, not the integrator's.
        """
        eigenvalues = np.linalg.eigvals(self.linearise(q_rad))
        eigenvalues = np.minimum(eigenvalues.real, 0.0) + 1j * eigenvalues.imag
        steps = np.geomspace(1e-7, 1.0, 3000)
        z = steps[:, None] * eigenvalues[None, :]
        growth = np.abs(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24).max(axis=1)
        unstable = np.nonzero(growth > 1.0 + 1e-12)[0]
        if unstable.size == 0:
            return float(steps[-1])
        return float(steps[max(unstable[0] - 1, 0)])
